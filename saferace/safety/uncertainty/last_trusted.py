"""What a robust filter knows of the lane state: the set carried from the car's start,
narrowed by the frames it trusts, and the box the recent ones agree on.

Every step the set (:mod:`~saferace.safety.uncertainty.dead_reckoning`) is carried to the
car, and the frame is judged: trusted where the state source raises no alarm and its
interval meets the set. An interval that does not meet the carried set at all is evidence
against the network, not against odometry, so that frame counts as in doubt
(:meth:`LastTrusted.consistent`). The filter certifies over the set alone while in doubt,
and over its meet with the box the recent trusted intervals vote for otherwise
(:mod:`~saferace.safety.uncertainty.interval_votes`;
:class:`~saferace.safety.cbf.filter.SafetyFilter`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from saferace.faults.wrapper import declared
from saferace.names import (
    ACTUATION_DELAY_ATTRIBUTE,
    CAMERA_LATENCY_ATTRIBUTE,
    ODOMETRY_ERROR_ATTRIBUTE,
)
from saferace.safety.uncertainty.dead_reckoning import (
    NARROWING_WIDTHS,
    START_TOLERANCE,
    DeadReckoning,
    car_pose,
)
from saferace.safety.uncertainty.interval_votes import RecentIntervals

if TYPE_CHECKING:
    import gymnasium as gym

    from saferace.track.raceline import ReferenceLine
    from saferace.track.track import Track

#: What a task's wrappers declare where its loop may be late (see :meth:`LastTrusted.of_task`).
LATE_LOOP_ATTRIBUTES = (ACTUATION_DELAY_ATTRIBUTE, CAMERA_LATENCY_ATTRIBUTE)


def cuts(carried: DeadReckoning | None, interval: tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether ``interval`` says something of the offset the ``carried`` set does not: it
    leaves out part of the set's ``e_y`` (always, without a set). An interval wider than
    the set (an unfamiliar look) would hold every point the set does and outvote nothing."""
    if carried is None:
        return True
    return bool(interval[0][0] > carried.lower[0] or interval[1][0] < carried.upper[0])


def offset_with_heading(
    interval: tuple[np.ndarray, np.ndarray], carried: DeadReckoning | None
) -> tuple[np.ndarray, np.ndarray]:
    """The box of ``[e_y, e_psi]`` a trusted ``interval`` is kept as: its offset, and its
    heading met with the ``carried`` set's. The network's heading is +-0.4 rad on a
    circuit's straight and the set's a few mrad; carried, every radian of a box's heading
    spreads its offset by the distance driven."""
    lower, upper = (np.asarray(bound, float)[:2].copy() for bound in interval)
    if carried is not None:
        lower[1], upper[1] = max(lower[1], carried.lower[1]), min(upper[1], carried.upper[1])
    return lower, upper


class LastTrusted:
    """The set of ``[e_y, e_psi]`` a filter on ``track`` carries forward from the car's
    start on the task's ``reference`` line: carried by odometry every step and narrowed by
    every interval it trusts; and the recent trusted intervals, carried beside it. Both are
    carried for an odometry whose distance and turn may be off by the fraction
    ``odometry_scale_error`` (:func:`~saferace.safety.uncertainty.dead_reckoning.
    scale_growth`). The box certified over meets the set with the intervals widened to
    ``certified_widths`` times their width (:meth:`held`)."""

    def __init__(
        self,
        track: Track,
        reference: ReferenceLine,
        odometry_scale_error: float = 0.0,
        certified_widths: float = 1.0,
    ) -> None:
        if not 0.0 <= odometry_scale_error < 1.0:
            raise ValueError(f"odometry_scale_error must be in [0, 1), got {odometry_scale_error}")
        if certified_widths < 1.0:
            raise ValueError(f"certified_widths must be >= 1, got {certified_widths}")
        self.track = track
        self.reference = reference
        self.odometry_scale_error = odometry_scale_error
        self.certified_widths = certified_widths
        self.reckoning: DeadReckoning | None = None
        self.recent = RecentIntervals()

    @classmethod
    def of_task(cls, env: gym.Env) -> LastTrusted:
        """The set of ``env``'s task: its track and reference line, and the odometry's error
        its wrappers declare (:data:`~saferace.names.ODOMETRY_ERROR_ATTRIBUTE`; none: the
        simulator's, exact). A set carried for a smaller error than the car's odometry has
        loses the car within seconds on bends (``tests/test_faulty_odometry.py``); one
        carried for a larger one grows in heading on every bend, and stopped the weaving
        driver for 22 s of 40 on Yas Marina.

        Where the loop may be late, its actuators
        (:data:`~saferace.names.ACTUATION_DELAY_ATTRIBUTE`) or its camera
        (:data:`~saferace.names.CAMERA_LATENCY_ATTRIBUTE`), the box certified over meets the
        set with the intervals widened as the set keeps them
        (:data:`~saferace.safety.uncertainty.dead_reckoning.NARROWING_WIDTHS`): a command
        certified on a frame whose interval misses the car acts for steps after, or the
        frame that would undo it comes steps later, where on time the next frame undoes it
        at once. Certified on the bare intervals, the drifting driver on Brands Hatch
        widened to 2.6 m left the lane for 0.1 s with its commands 150 ms late and for
        0.15 s with its frames 200 ms late, each after frames whose intervals ended
        0.15-0.2 m short of the car."""
        base = env.unwrapped
        error = declared(env, ODOMETRY_ERROR_ATTRIBUTE)
        late = any(declared(env, name) > 0 for name in LATE_LOOP_ATTRIBUTES)
        widths = NARROWING_WIDTHS if late else 1.0
        return cls(base.track, base.reference, error, widths)  # type: ignore[attr-defined]

    def reset(self, info: dict[str, Any] | None = None) -> None:
        """No set, or with ``info`` the start's (:meth:`start`); no recent interval."""
        self.reckoning = None
        self.recent.reset()
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
        pose, s_m = car_pose(info), float(info["s_m"])
        return last.carried(pose, s_m, self.track.centerline, self.odometry_scale_error)

    def update(
        self, alarm: bool, interval: tuple[np.ndarray, np.ndarray], info: dict[str, Any]
    ) -> tuple[bool, DeadReckoning | None]:
        """Carry the set and the recent intervals to the car in ``info``, judge this frame
        and keep what the next step carries (:meth:`keep`). Returns whether the frame is
        trusted (no ``alarm``, and its ``interval`` meets the set) and the set the filter
        certifies over (:meth:`held`; None: none was started)."""
        carried = self.carried(info)
        pose, s_m = car_pose(info), float(info["s_m"])
        self.recent.carry(pose, s_m, self.track.centerline, self.odometry_scale_error)
        trusted = not alarm and self.consistent(carried, interval)
        if trusted and cuts(carried, interval):
            self.recent.add(offset_with_heading(interval, carried), pose, s_m)
        self.keep(trusted, interval, carried)
        return trusted, self.held(trusted, interval, carried)

    @staticmethod
    def consistent(carried: DeadReckoning | None, interval: tuple[np.ndarray, np.ndarray]) -> bool:
        """Whether a frame's ``interval`` meets the ``carried`` set (True without one)."""
        return carried is None or carried.meets(*interval)

    def held(
        self,
        trusted: bool,
        interval: tuple[np.ndarray, np.ndarray],
        carried: DeadReckoning | None,
    ) -> DeadReckoning | None:
        """The ``carried`` set met with the box the recent trusted intervals vote for
        (:meth:`RecentIntervals.voted`) and, where the frame is ``trusted``, with its own
        ``interval`` (each widened to ``certified_widths`` times its width), each only where
        it meets what the others left (a frame the majority outvotes does not narrow). In
        doubt the votes count only where the set holds all of their box: a network the
        odometry contradicts (its intervals reaching beyond the set) is wrong in the votes
        too, and the set alone holds the car."""
        if carried is None:
            return None
        voted = self.recent.voted()
        if voted is not None and not trusted and not carried.holds(*voted):
            voted = None
        held = carried
        for box in ([] if voted is None else [voted]) + ([interval] if trusted else []):
            if held.meets(*box):
                held = held.narrowed(*box, widths=self.certified_widths)
        return held

    def keep(
        self,
        trusted: bool,
        interval: tuple[np.ndarray, np.ndarray],
        carried: DeadReckoning | None,
    ) -> None:
        """Keep what the next step carries: the ``carried`` set (None: none was started),
        narrowed to this frame's ``interval`` where that was ``trusted`` and meets it."""
        if carried is not None and trusted and carried.meets(*interval):
            carried = carried.narrowed(*interval)
        self.reckoning = carried
