"""The lane state's set carried forward by odometry and the map from the car's start.

When the state source is in doubt (its monitor raises), what the car still knows is how it
moved: its odometry over the control step (the body-frame displacement ``(dx, dy)`` and yaw
change ``dyaw``, what wheel speeds and an IMU integrated at the simulator's rate measure;
never its pose on the map), its arc length ``s`` (which the filter takes from the task, as
it does the map's widths and curvature there) and the map. The same holds before any frame
was trusted: the car starts on its reference line at the start line, a pose the task
defines, so a set exists from the first step
(:class:`~saferace.safety.uncertainty.last_trusted.LastTrusted` keeps it).

With ``s`` known the carrying is exact geometry (:func:`carried_states`). The centre
line's pose ``(x, y, theta)`` at the step's two arc lengths is the map's; a car at ``[e_y,
e_psi]`` there heads ``theta + e_psi``, so its move lands it at a known point of the plane,
whose offset along the new normal is the new ``e_y``, and

    e_psi' = e_psi + dyaw - (theta' - theta)

the gyro's turn less the lane's. Each corner of the ``[e_y, e_psi]`` box is carried so,
and the box of the carried corners, grown by the odometry's error bound per metre driven
(:data:`ERROR_PER_M`: the simulator's odometry has none, so this is a real car's), holds
the car. The heading's width stays what the start gave it plus the gyro's drift. It
matters twice: an uncertain heading moves the corners' offsets apart by ``L sin`` of it
every step, and a filter certifying over a heading of +-0.2 rad (the generic network's
interval on ``lab``) found no steering that held both of its extremes and stopped the car
within 8 m. A car at rest grows no error: its set stays where it stopped.

A trusted frame's interval narrows the set to their intersection
(:meth:`DeadReckoning.narrowed`), the interval first widened to :data:`NARROWING_WIDTHS`
times its width about its centre: an interval holds the truth on about 95% of the frames,
and a set narrowed by every frame's would lose the car on the first frame it missed and
keep it lost (replayed in ``tests/test_dead_reckoning.py``: a network 0.5 m off with an
interval of +-0.3 m pulled a set narrowed to its bare interval away from the car within
2 s). Widened, an interval off by less than twice its own half width still holds the car,
and the set stays no wider than the widened interval.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from saferace.names import ODOMETRY_POSE_KEY
from saferace.track.frenet import wrap_angle
from saferace.track.odometry import odometry_step

if TYPE_CHECKING:
    from saferace.track.path import ClosedPath

#: How far a carried corner may be off the truth per metre driven, ``[e_y (m/m), e_psi
#: (rad/m)]``. The simulator's odometry is exact (``benchmarks/dead_reckoning_error.py``
#: measures the carrying's error at about 1e-9 per metre), so these are a real car's: a
#: millimetre per metre of sideways slip its wheels do not see, and a gyro drifting
#: 5e-5 rad per metre (about 50 deg/h at 5 m/s, a consumer MEMS part).
ERROR_PER_M = np.array([0.001, 5e-5])
#: How far the car may be off its reference line at the start, ``[e_y (m), e_psi (rad)]``:
#: the task places it on the line, heading along it (the physics moves it by well under a
#: millimetre and a milliradian before the first step).
START_TOLERANCE = np.array([0.01, 0.002])
#: How many times its own width a trusted interval is widened to before it narrows the
#: carried set (about its centre; see the module).
NARROWING_WIDTHS = 2.0


def car_pose(info: dict) -> np.ndarray:
    """``(x, y, yaw)`` of the car as its odometry integrates it: only its change over a step
    is used (:func:`~saferace.track.odometry.odometry_step`), never where it is on the map.
    A fault wrapper gives its faulty odometry's under :data:`~saferace.names.ODOMETRY_POSE_KEY`
    (:mod:`saferace.faults`); without one the odometry is the simulator's, exact."""
    pose = info.get(ODOMETRY_POSE_KEY)
    if pose is None:
        pose = (info["x_m"], info["y_m"], info["yaw_rad"])
    return np.array(pose, dtype=float)


def centre_pose(centerline: ClosedPath, s_m: float) -> np.ndarray:
    """``(x, y, theta)`` of the centre line at arc length ``s_m``: the map's."""
    x, y, dx, dy, _, _ = centerline.eval_scalar(s_m)
    return np.array([x, y, math.atan2(dy, dx)])


def carried_states(
    e_y_m: np.ndarray,
    e_psi_rad: np.ndarray,
    step: np.ndarray,
    centre_from: np.ndarray,
    centre_to: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``(e_y, e_psi)`` after the odometry ``step`` (:func:`odometry_step`) from the given
    states, the centre line's pose (:func:`centre_pose`) at the step's start ``centre_from``
    and at its end ``centre_to`` (exact, see the module)."""
    dx, dy, dyaw = (float(v) for v in step)
    x0, y0, theta0 = (float(v) for v in centre_from)
    x1, y1, theta1 = (float(v) for v in centre_to)
    yaw = theta0 + e_psi_rad
    x = x0 - math.sin(theta0) * e_y_m + np.cos(yaw) * dx - np.sin(yaw) * dy
    y = y0 + math.cos(theta0) * e_y_m + np.sin(yaw) * dx + np.cos(yaw) * dy
    e_y = (y - y1) * math.cos(theta1) - (x - x1) * math.sin(theta1)
    return e_y, e_psi_rad + dyaw - wrap_angle(theta1 - theta0)


def scale_growth(step: np.ndarray, e_psi_rad: np.ndarray, scale_error: float) -> np.ndarray:
    """``[e_y (m), e_psi (rad)]`` a carried set grows by in a ``step`` measured up to the
    fraction ``scale_error`` of the truth off (per box of a stack, its carried headings
    ``e_psi_rad`` along the last axis). Measured ``1 - scale_error`` times the truth, the
    truth is ``scale_error / (1 - scale_error)`` of the measure beyond it. The turn's error is
    the heading's; a distance off moves the car along its heading, across the lane by at
    most ``sin`` of its angle to the lane (at most its heading's plus the turn), and the
    turn's error swings it by the distance driven."""
    relative = scale_error / (1.0 - scale_error)
    step_m, turn_rad = math.hypot(step[0], step[1]), abs(float(step[2]))
    angle = np.minimum(np.abs(e_psi_rad).max(axis=-1) + turn_rad, 0.5 * math.pi)
    across_m = relative * step_m * (np.sin(angle) + turn_rad)
    return np.stack([across_m, np.full_like(across_m, relative * turn_rad)], axis=-1)


@dataclass(frozen=True)
class DeadReckoning:
    """A box ``lower .. upper`` of ``[e_y, e_psi]`` that holds the car, ``driven_m`` metres
    after the last trusted frame, with the ``pose`` the next step's odometry starts from
    (only the move from it is used) and the arc length ``s_m`` there."""

    lower: np.ndarray
    upper: np.ndarray
    pose: np.ndarray
    s_m: float
    driven_m: float = 0.0

    @classmethod
    def trusted(
        cls, lower: np.ndarray, upper: np.ndarray, pose: np.ndarray, s_m: float
    ) -> DeadReckoning:
        """The box a trusted frame's interval ``lower .. upper`` (its ``[e_y, e_psi]``) is."""
        return cls(
            np.asarray(lower, float)[:2].copy(),
            np.asarray(upper, float)[:2].copy(),
            np.asarray(pose, float).copy(),
            float(s_m),
        )

    def carried(
        self, pose: np.ndarray, s_m: float, centerline: ClosedPath, scale_error: float = 0.0
    ) -> DeadReckoning:
        """The box with the car now at ``pose`` and ``s_m``: its corners carried by the
        step's odometry along the map's ``centerline`` (:func:`carried_states`), grown by
        :data:`ERROR_PER_M` for the distance driven and for an odometry whose distance and
        turn may be off by the fraction ``scale_error`` (:func:`scale_growth`). A stack of
        boxes (``lower`` and ``upper`` of shape ``(n, 2)``) is carried box by box."""
        step = odometry_step(self.pose, pose)
        lower, upper = self.lower, self.upper
        e_y, e_psi = carried_states(
            np.stack([lower[..., 0], lower[..., 0], upper[..., 0], upper[..., 0]], axis=-1),
            np.stack([lower[..., 1], upper[..., 1], lower[..., 1], upper[..., 1]], axis=-1),
            step,
            centre_pose(centerline, self.s_m),
            centre_pose(centerline, s_m),
        )
        step_m = math.hypot(step[0], step[1])
        growth = ERROR_PER_M * step_m
        if scale_error:  # an exact odometry's steps (every fault-free task's) grow no more
            growth = growth + scale_growth(step, e_psi, scale_error)
        return DeadReckoning(
            np.stack([e_y.min(axis=-1), e_psi.min(axis=-1)], axis=-1) - growth,
            np.stack([e_y.max(axis=-1), e_psi.max(axis=-1)], axis=-1) + growth,
            np.asarray(pose, float).copy(),
            float(s_m),
            self.driven_m + step_m,
        )

    def interval(self, kappa_radpm: float) -> tuple[np.ndarray, np.ndarray]:
        """``(lower, upper)`` of ``[e_y, e_psi, kappa]``, the curvature the map's."""
        return np.append(self.lower, kappa_radpm), np.append(self.upper, kappa_radpm)

    def meets(self, lower: np.ndarray, upper: np.ndarray) -> bool:
        """Whether the box ``lower .. upper`` (of ``[e_y, e_psi, ...]``) meets this set."""
        return bool(
            np.all(np.asarray(lower, float)[:2] <= self.upper)
            and np.all(self.lower <= np.asarray(upper, float)[:2])
        )

    def holds(self, lower: np.ndarray, upper: np.ndarray) -> bool:
        """Whether the box ``lower .. upper`` (of ``[e_y, e_psi, ...]``) lies in this set."""
        return bool(
            np.all(self.lower <= np.asarray(lower, float)[:2])
            and np.all(np.asarray(upper, float)[:2] <= self.upper)
        )

    def narrowed(
        self, lower: np.ndarray, upper: np.ndarray, widths: float = NARROWING_WIDTHS
    ) -> DeadReckoning:
        """This set cut to the box ``lower .. upper`` it meets (:meth:`meets`), widened to
        ``widths`` times its width about its centre first."""
        lower, upper = np.asarray(lower, float)[:2], np.asarray(upper, float)[:2]
        centre, half = 0.5 * (lower + upper), 0.5 * widths * (upper - lower)
        return dataclasses.replace(
            self,
            lower=np.maximum(self.lower, centre - half),
            upper=np.minimum(self.upper, centre + half),
        )
