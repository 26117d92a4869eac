"""The lane state's last trusted interval carried forward by odometry and the map.

When the state source is in doubt (its monitor raises), what the car still knows is how it
moved: its odometry over the control step (the body-frame displacement ``(dx, dy)`` and yaw
change ``dyaw``, what wheel speeds and an IMU integrated at the simulator's rate measure;
never its pose on the map) and the map's curvature where it is. The same holds before any
frame was trusted: the car starts on its reference line at the start line, a pose the task
defines, so a set exists from the first step (:meth:`LastTrusted.start`). A car at ``[e_y, e_psi]``
that moves by ``(dx, dy, dyaw)`` along a centre line of curvature ``kappa`` ends at

    ds      = L cos(phi) / (1 - kappa e_y) * a / sin(a),   a = kappa ds / 2
    phi     = e_psi + atan2(dy, dx) - a,                   L = |(dx, dy)|
    e_y'    = e_y + L sin(phi)
    e_psi'  = e_psi + dyaw - kappa ds

(the chord against the centre line's tangent halfway, and an arc's length over its
chord's). Each corner of the last trusted
``[e_y, e_psi]`` box is carried so, and the box of the carried corners, grown by the
carrying's error bound per metre driven, holds the car: the bound was measured, not
assumed (``benchmarks/dead_reckoning_error.py``). A car at rest grows no error: its set
stays where it stopped. The safety filter certifies from this set while the doubt lasts,
so a heading error inherited from the last trusted frame is still steered out, and stops
the car where the set no longer fits the lane (:class:`~saferace.safety.cbf.filter.SafetyFilter`).

The set is carried every step, trusted or not, and a trusted frame's interval narrows it.
An interval that does not meet the carried set at all is evidence against the network,
not against odometry: the frame counts as in doubt (:meth:`LastTrusted.consistent`). One
that meets it narrows it to their intersection, the interval first widened to
:data:`NARROWING_WIDTHS` times its width about its centre: an interval holds the truth on
about 95% of the frames, and a set narrowed by every frame's would lose the car on the
first frame it missed and keep it lost (replayed in ``tests/test_dead_reckoning.py``: a
network 0.5 m off with an interval of +-0.3 m pulled a set narrowed to its bare interval
away from the car within 2 s). Widened, an interval off by less than twice its own half
width still holds the car, and the set stays no wider than the widened interval. The
filter certifies a trusted frame on its own interval, as before: certified on the set
narrowed by the widened interval, the expert stood for 27 s of 30 on ``lab``'s 0.8 m lane,
which that set no longer fitted.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from saferace.track.frenet import wrap_arc

if TYPE_CHECKING:
    from saferace.track.raceline import ReferenceLine
    from saferace.track.track import Track

#: How far a carried corner may be off the truth per metre driven, ``[e_y (m/m), e_psi
#: (rad/m)]``: about three times the worst one-step error measured over 2,840 steps of
#: four agents on three unseen random tracks (3.3e-4 m and 1.4e-3 rad per metre, by
#: ``benchmarks/dead_reckoning_error.py``): what the step's chord and the map's curvature
#: halfway leave out.
ERROR_PER_M = np.array([0.001, 0.005])
#: The stretch ``1 - kappa e_y`` is kept above this, as off a tight bend's inside.
MIN_STRETCH = 0.1
#: How far the car may be off its reference line at the start, ``[e_y (m), e_psi (rad)]``:
#: the task places it on the line, heading along it (the physics moves it by well under a
#: millimetre before the first step).
START_TOLERANCE = np.array([0.02, 0.02])
#: How many times its own width a trusted interval is widened to before it narrows the
#: carried set (about its centre; see the module).
NARROWING_WIDTHS = 2.0


def car_pose(info: dict) -> np.ndarray:
    """``(x, y, yaw)`` of the car in ``info``: only its change over a step is used, as the
    car's odometry measures it (:func:`odometry_step`), never where it is on the map."""
    return np.array([info["x_m"], info["y_m"], info["yaw_rad"]], dtype=float)


def midway_s(s_from_m: float, s_to_m: float, length_m: float) -> float:
    """The arc length halfway along a step from ``s_from_m`` to ``s_to_m`` on a lap of
    ``length_m`` (across the start line too)."""
    return (s_from_m + 0.5 * float(wrap_arc(s_to_m - s_from_m, length_m))) % length_m


def odometry_step(pose_from: np.ndarray, pose_to: np.ndarray) -> np.ndarray:
    """``(dx, dy, dyaw)``: the move from ``pose_from`` to ``pose_to`` (each ``(x, y,
    yaw)``) in the body frame at its start, as the car's odometry measures it."""
    x0, y0, yaw0 = (float(v) for v in pose_from)
    x1, y1, yaw1 = (float(v) for v in pose_to)
    cos, sin = math.cos(yaw0), math.sin(yaw0)
    dx, dy = x1 - x0, y1 - y0
    dyaw = (yaw1 - yaw0 + math.pi) % (2.0 * math.pi) - math.pi
    return np.array([cos * dx + sin * dy, -sin * dx + cos * dy, dyaw])


def carried_states(
    e_y_m: np.ndarray, e_psi_rad: np.ndarray, step: np.ndarray, kappa_radpm: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(e_y, e_psi)`` after the odometry ``step`` (:func:`odometry_step`) from the given
    states, on a centre line of curvature ``kappa_radpm`` (see the module; two fixed-point
    passes, exact for a car that follows a parallel of the centre line)."""
    dx, dy, dyaw = (float(v) for v in step)
    chord_m, chord_rad = math.hypot(dx, dy), math.atan2(dy, dx)
    stretch = np.maximum(1.0 - kappa_radpm * e_y_m, MIN_STRETCH)
    ds = chord_m * np.cos(e_psi_rad + chord_rad) / stretch
    for _ in range(2):
        half = 0.5 * kappa_radpm * ds  # the tangent's turn to halfway
        phi = e_psi_rad + chord_rad - half
        ds = chord_m * np.cos(phi) / stretch * _arc_per_chord(half)
    return e_y_m + chord_m * np.sin(phi), e_psi_rad + dyaw - kappa_radpm * ds


def _arc_per_chord(half_angle_rad: np.ndarray) -> np.ndarray:
    """An arc's length over its chord's, ``a / sin a`` for half its angle ``a``."""
    angle = np.abs(half_angle_rad)
    return np.where(angle < 1e-6, 1.0, angle / np.sin(np.maximum(angle, 1e-6)))


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

    def carried(self, pose: np.ndarray, s_m: float, kappa_radpm: float) -> DeadReckoning:
        """The box with the car now at ``pose`` and ``s_m``: its corners carried by the
        step's odometry on the map's curvature ``kappa_radpm`` (midway along the step, see
        :func:`midway_s`), grown by :data:`ERROR_PER_M` for the distance driven."""
        step = odometry_step(self.pose, pose)
        corners = np.array(list(itertools.product(*zip(self.lower, self.upper, strict=True))))
        e_y, e_psi = carried_states(corners[:, 0], corners[:, 1], step, kappa_radpm)
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
        s_m = float(info["s_m"])
        midway = midway_s(last.s_m, s_m, self.track.length_m)
        return last.carried(car_pose(info), s_m, self.track.centerline.curvature_scalar(midway))

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
