"""The lane state's set carried forward by odometry and the map from the car's start.

When the state source is in doubt (its monitor raises), what the car still knows is how it
moved: its odometry over the control step (the body-frame displacement ``(dx, dy)`` and yaw
change ``dyaw``, what wheel speeds and an IMU integrated at the simulator's rate measure;
never its pose on the map), its arc length ``s`` (which the filter takes from the task, as
it does the map's widths and curvature there) and the map. The same holds before any frame
was trusted: the car starts on its reference line at the start line, a pose the task
defines, so a set exists from the first step (:meth:`LastTrusted.start`).

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
within 8 m. A car at rest grows no
error: its set stays where it stopped. The safety filter certifies from this set while the
doubt lasts, and from its intersection with a trusted frame's interval otherwise
(:class:`~saferace.safety.cbf.filter.SafetyFilter`).

The set is carried every step, trusted or not, and a trusted frame's interval narrows it.
An interval that does not meet the carried set at all is evidence against the network,
not against odometry: the frame counts as in doubt (:meth:`LastTrusted.consistent`). One
that meets it narrows it to their intersection, the interval first widened to
:data:`NARROWING_WIDTHS` times its width about its centre: an interval holds the truth on
about 95% of the frames, and a set narrowed by every frame's would lose the car on the
first frame it missed and keep it lost (replayed in ``tests/test_dead_reckoning.py``: a
network 0.5 m off with an interval of +-0.3 m pulled a set narrowed to its bare interval
away from the car within 2 s). Widened, an interval off by less than twice its own half
width still holds the car, and the set stays no wider than the widened interval.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from saferace.track.frenet import wrap_angle

if TYPE_CHECKING:
    from saferace.track.path import ClosedPath
    from saferace.track.raceline import ReferenceLine
    from saferace.track.track import Track

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
    """``(x, y, yaw)`` of the car in ``info``: only its change over a step is used, as the
    car's odometry measures it (:func:`odometry_step`), never where it is on the map."""
    return np.array([info["x_m"], info["y_m"], info["yaw_rad"]], dtype=float)


def centre_pose(centerline: ClosedPath, s_m: float) -> np.ndarray:
    """``(x, y, theta)`` of the centre line at arc length ``s_m``: the map's."""
    x, y, dx, dy, _, _ = centerline.eval_scalar(s_m)
    return np.array([x, y, math.atan2(dy, dx)])


def odometry_step(pose_from: np.ndarray, pose_to: np.ndarray) -> np.ndarray:
    """``(dx, dy, dyaw)``: the move from ``pose_from`` to ``pose_to`` (each ``(x, y,
    yaw)``) in the body frame at its start, as the car's odometry measures it."""
    x0, y0, yaw0 = (float(v) for v in pose_from)
    x1, y1, yaw1 = (float(v) for v in pose_to)
    cos, sin = math.cos(yaw0), math.sin(yaw0)
    dx, dy = x1 - x0, y1 - y0
    dyaw = wrap_angle(yaw1 - yaw0)
    return np.array([cos * dx + sin * dy, -sin * dx + cos * dy, dyaw])


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

    def carried(self, pose: np.ndarray, s_m: float, centerline: ClosedPath) -> DeadReckoning:
        """The box with the car now at ``pose`` and ``s_m``: its corners carried by the
        step's odometry along the map's ``centerline`` (:func:`carried_states`), grown by
        :data:`ERROR_PER_M` for the distance driven."""
        step = odometry_step(self.pose, pose)
        corners = np.array(list(itertools.product(*zip(self.lower, self.upper, strict=True))))
        e_y, e_psi = carried_states(
            corners[:, 0],
            corners[:, 1],
            step,
            centre_pose(centerline, self.s_m),
            centre_pose(centerline, s_m),
        )
        carried = np.column_stack([e_y, e_psi])
        step_m = math.hypot(step[0], step[1])
        growth = ERROR_PER_M * step_m
        return DeadReckoning(
            carried.min(axis=0) - growth,
            carried.max(axis=0) + growth,
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


class LastTrusted:
    """The set of ``[e_y, e_psi]`` a filter on ``track`` carries forward from the car's
    start on the task's ``reference`` line: carried by odometry every step and narrowed by
    every interval it trusts."""

    def __init__(self, track: Track, reference: ReferenceLine) -> None:
        self.track = track
        self.reference = reference
        self.reckoning: DeadReckoning | None = None

    def reset(self, info: dict[str, Any] | None = None) -> None:
        """No set, or with ``info`` the start's (:meth:`start`)."""
        self.reckoning = None
        if info is not None:
            self.start(info)

    def start(self, info: dict[str, Any]) -> None:
        """The set at the start: the task's start pose, on its reference line heading along
        it at the car's arc length, within :data:`START_TOLERANCE`; the car as in ``info``."""
        s_m = float(info["s_m"])
        centre = np.array(
            [self.reference.offset_at(s_m), self.reference.heading_offset_at(s_m)], float
        )
        self.reckoning = DeadReckoning.trusted(
            centre - START_TOLERANCE, centre + START_TOLERANCE, car_pose(info), float(info["s_m"])
        )

    def carried(self, info: dict[str, Any]) -> DeadReckoning | None:
        """The set carried to the car in ``info``; None where none was started."""
        last = self.reckoning
        if last is None:
            return None
        return last.carried(car_pose(info), float(info["s_m"]), self.track.centerline)

    def update(
        self, alarm: bool, interval: tuple[np.ndarray, np.ndarray], info: dict[str, Any]
    ) -> tuple[bool, DeadReckoning | None]:
        """Carry the set to the car in ``info``, judge this frame and keep what the next
        step carries (:meth:`keep`): whether the frame is trusted (no ``alarm``, and its
        ``interval`` meets the set) and the set carried to it (None: none was started)."""
        carried = self.carried(info)
        trusted = not alarm and self.consistent(carried, interval)
        self.keep(trusted, interval, carried, info)
        return trusted, carried

    @staticmethod
    def consistent(carried: DeadReckoning | None, interval: tuple[np.ndarray, np.ndarray]) -> bool:
        """Whether a frame's ``interval`` meets the ``carried`` set (True without one)."""
        return carried is None or carried.meets(*interval)

    def keep(
        self,
        trusted: bool,
        interval: tuple[np.ndarray, np.ndarray],
        carried: DeadReckoning | None,
        info: dict[str, Any],
    ) -> DeadReckoning | None:
        """Keep what the next step carries, and return it: the ``carried`` set (None: none
        was started), narrowed to this frame's ``interval`` where that was ``trusted`` and
        meets it."""
        if carried is not None and trusted and carried.meets(*interval):
            carried = carried.narrowed(*interval)
        self.reckoning = carried
        return carried
