"""The expert MPC in traffic: it plans around the opponents in ``info``, passing where the
lane has room for the pass and following where it has not.

- **Prediction.** Each opponent goes on at its speed along its heading (``speed
  cos(e_psi)``), on the line it has kept for the last ``HISTORY_S``: its offset from the
  centre line or from the racing line, whichever has varied less (a car on the racing
  line sweeps across the lane from one corner to the next), give or take
  ``PREDICTION_MARGIN_M``; with less history, anywhere between the two.
- **Whether to pass** is decided every step over ``PASS_HORIZON_S``, longer than the
  MPC's plan: the ego, accelerating at ``PASS_ACCEL_MPS2`` to its reference speed, passes
  on a side that keeps its centre ``PASS_WIDTH_M`` from the opponent's band, inside the
  lane, wherever it is predicted beside the opponent and behind it, until level (from there
  on the line is its own: a car that moves across into it is at fault), or, behind a car
  that leaves room (``leaves_room`` in its info: a ``racer``), until alongside it, within
  ``PASS_LENGTH_M``: from there that car keeps its side. It takes the side
  it is on if that has room, else the other, keeps a side it chose while that has room,
  and after giving one up falls in behind for ``RETRY_AFTER_S``.
- **Passing.** From ``LEAD_IN_M`` before it is beside the opponent until past it, the
  plan's lateral bound keeps it on its side of the band, moving over no steeper than
  ``MOVE_OVER_SLOPE``, and its line there is the middle of the room left. Once alongside
  it keeps its own side whatever the room: it never cuts across the opponent's nose.
- **Following.** Until the bounds clear the car ahead (on every stage where it follows, or
  has no room beside it) the speed is capped so that braking at ``FOLLOW_BRAKING_MPS2`` it
  stops ``FOLLOW_GAP_M`` behind the opponent braking as hard; closer, it drops back. A car
  behind it is never followed (braking for it would only invite it in).

The bounds and caps are soft, as the lane's are; the safety filter's car barriers are what
guarantee clearance.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from saferace.agents.mpc import MPCExpert
from saferace.envs.reference_lines import reference_line
from saferace.safety.traffic.car_barriers import BUMPER_HALF_LENGTH_M, BUMPER_HALF_WIDTH_M
from saferace.track.frenet import wrap_arc
from saferace.track.raceline import ReferenceLine

#: Along the track, the ego is beside an opponent while their centres are this close (m):
#: a bumper's length plus a margin.
PASS_LENGTH_M = 2.0 * BUMPER_HALF_LENGTH_M + 0.15
#: Across it, the ego's centre keeps this far from the opponent's (m): a bumper's width plus
#: a margin.
PASS_WIDTH_M = 2.0 * BUMPER_HALF_WIDTH_M + 0.08
#: Behind an opponent, the ego keeps to its passing side from this far before it is beside
#: (m), so that it moves over while still behind.
LEAD_IN_M = 1.0
#: The steepest the bounds and the line ask the car to move over (m across per m along at
#: its speed, 0.6 m/s at 4 m/s): a pass chosen late is a gentle move over while the
#: following cap holds the car back, and the way back to its line after a pass no swerve;
#: a car standing still is not asked to move sideways.
MOVE_OVER_SLOPE = 0.15
#: How far ahead a pass is planned (s), sampled every ``PASS_STEP_S``.
PASS_HORIZON_S = 4.0
PASS_STEP_S = 0.1
#: The acceleration a planned pass assumes, up to the reference speed (m/s^2).
PASS_ACCEL_MPS2 = 2.0
#: After giving up a pass, the ego follows for this long before choosing a side again (s).
RETRY_AFTER_S = 1.0
#: How long a history of each opponent's offsets tells the line it keeps (s), and the margin
#: around that line's prediction (m).
HISTORY_S = 1.0
PREDICTION_MARGIN_M = 0.03
#: Following: the gap between centres it stops at (m) and the braking it plans with (m/s^2;
#: the car brakes at about 4).
FOLLOW_GAP_M = 0.8
FOLLOW_BRAKING_MPS2 = 3.0
#: Closer than the following gap, the ego drops back this fast per metre short (1/s).
FALL_BACK_PER_S = 2.0
#: Opponents further ahead than this (m) or behind are ignored.
LOOK_AHEAD_M = 12.0
LOOK_BEHIND_M = 1.0


class TrafficExpert(MPCExpert):
    """The expert MPC that passes or follows the opponents in ``info["opponents"]``."""

    speed_rows = True
    #: This step's plan for each opponent near the car (set by :meth:`act`).
    _passes: list[PassPlan] = []  # noqa: RUF012 - replaced, never mutated
    _stage_caps_mps = np.full(0, np.inf)
    _offset_targets = np.zeros(0)
    _target_sides = np.zeros(0, dtype=int)
    _reachable_m = np.zeros(0)
    _ego_e_y = 0.0
    _ego_speed_mps = 0.0

    @cached_property
    def racing_line(self) -> ReferenceLine:
        """The line opponents are predicted to drift to."""
        return reference_line(self.track, "racing")

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        #: Each opponent's last offsets from the centre line and from the racing line, and
        #: the side the ego passes it on.
        self._histories: dict[str, deque[tuple[float, float]]] = {}
        self._sides: dict[str, int] = {}
        #: The side the ego gave up on each opponent, and until when it falls in behind (s).
        self._given_up: dict[str, tuple[int, float]] = {}
        self._time_s = 0.0

    def act(self, observation: Any, info: dict[str, Any]) -> np.ndarray:
        if info.get("time_s", 0.0) == 0.0:
            self._histories, self._sides, self._given_up = {}, {}, {}
        self._time_s = float(info.get("time_s", 0.0))
        ego_s = float(info["s_m"])
        self._ego_e_y = float(info["e_y_m"])
        self._ego_speed_mps = float(info["v_x_mps"])
        near = opponents_near(info.get("opponents", ()))
        names = {opponent.name for opponent in near}
        for states in (self._histories, self._sides, self._given_up):  # out of reach: forget
            for name in set(states) - names:
                del states[name]
        self._passes = []
        for opponent in near:
            self.remember(opponent)
            self._passes.append(self.plan_for(opponent, ego_s))
        return super().act(observation, info)

    def plan_for(self, opponent: NearOpponent, ego_s: float) -> PassPlan:
        """This step's :class:`PassPlan` for ``opponent`` (after :meth:`remember`)."""
        gap = float(wrap_arc(opponent.s_m - ego_s, self.track.length_m))
        offset = self._ego_e_y - opponent.e_y_m
        if gap <= -PASS_LENGTH_M:  # past it: free to take any line
            return PassPlan(opponent, 0, np.inf, False)
        if gap <= 0.0:  # alongside and ahead: keep to its own side, never brake for it
            return PassPlan(opponent, 1 if offset > 0.0 else -1, np.inf, False)
        rooms = self.pass_rooms(opponent, ego_s)
        side = self.choose_side(opponent, gap, offset, rooms)
        self._sides[opponent.name] = side
        follows = side == 0 or rooms[0 if side > 0 else 1] < 0.0
        return PassPlan(opponent, side, following_speed_mps(gap, opponent), follows)

    def pass_rooms(self, opponent: NearOpponent, ego_s: float) -> tuple[float, float]:
        """``(left, right)``: the least room (m) beside ``opponent`` for the ego's centre
        where the ego is predicted beside it and behind, until level, within
        ``PASS_HORIZON_S`` (negative: none); behind a car that leaves room, only where the
        ego gets alongside (``PASS_LENGTH_M`` behind: one sample)."""
        length = self.track.length_m
        times = PASS_STEP_S * np.arange(1, round(PASS_HORIZON_S / PASS_STEP_S) + 1)
        s_opponent = opponent.s_m + opponent.v_mps * times
        gaps = wrap_arc(s_opponent - self.reference_progress_m(ego_s, times), length)
        before = np.concatenate([[wrap_arc(opponent.s_m - ego_s, length)], gaps[:-1]])
        # until level or alongside, where it gets there even between two samples (a fast
        # car closing on a slow one); the first term is empty behind a car that leaves room
        there = PASS_LENGTH_M if opponent.leaves_room else 0.0
        crossed = (before > there) & (gaps <= there) & (before - gaps < 0.5 * length)
        beside = ((gaps > there) & (gaps < PASS_LENGTH_M)) | crossed
        upper, lower = self.lane_limits(s_opponent[beside] % length)
        band_low, band_high = self.predicted_band(opponent, s_opponent[beside])
        left_room = (upper - band_high - PASS_WIDTH_M).min(initial=np.inf)
        right_room = (band_low - PASS_WIDTH_M - lower).min(initial=np.inf)
        return float(left_room), float(right_room)

    def choose_side(
        self, opponent: NearOpponent, gap: float, offset: float, rooms: tuple[float, float]
    ) -> int:
        """+1 to pass ``opponent``, ``gap`` ahead, on the left, -1 on the right, 0 to follow
        it: alongside, its own side; behind, the side it chose before while that keeps
        room, else :func:`passing_side` (but not within ``RETRY_AFTER_S`` of giving a side
        up: the car first falls in behind)."""
        if gap < PASS_LENGTH_M:  # alongside: its own side, never across the nose
            return 1 if offset > 0.0 else -1
        chosen = self._sides.get(opponent.name, 0)
        if chosen and rooms[0 if chosen > 0 else 1] >= 0.0:
            return chosen
        if chosen:  # the pass no longer fits: fall in behind before choosing again
            self._given_up[opponent.name] = (chosen, self._time_s + RETRY_AFTER_S)
        if self.falling_in_from(opponent.name):
            return 0
        return passing_side(offset, *rooms)

    def falling_in_from(self, name: str) -> int:
        """The side the ego gave up passing opponent ``name`` on while it falls in behind
        (``RETRY_AFTER_S``), else 0."""
        side, until_s = self._given_up.get(name, (0, 0.0))
        return side if self._time_s < until_s else 0

    def reference_progress_m(self, s_m: float, times_s: np.ndarray) -> np.ndarray:
        """The ego's arc length at ``times_s`` (even steps from 0) accelerating from its
        speed at ``PASS_ACCEL_MPS2`` to its reference speed."""
        step_s = float(times_s[0])
        positions = np.empty(len(times_s))
        speed = self._ego_speed_mps
        for index in range(len(times_s)):
            reference = self.settings.speed_scale * float(
                self.reference.speed_at(s_m % self.track.length_m)
            )
            speed = min(speed + PASS_ACCEL_MPS2 * step_s, reference)
            s_m += speed * step_s
            positions[index] = s_m
        return positions

    def remember(self, opponent: NearOpponent) -> None:
        """Add the opponent's offsets from the centre line and the racing line to its
        history."""
        history = self._histories.setdefault(
            opponent.name, deque(maxlen=round(HISTORY_S / self.settings.dt_s))
        )
        racing = float(self.racing_line.offset_at(opponent.s_m % self.track.length_m))
        history.append((opponent.e_y_m, opponent.e_y_m - racing))

    def predicted_band(
        self, opponent: NearOpponent, s_m: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(lowest, highest)`` lateral offset of ``opponent`` at arc lengths ``s_m``, on
        the line its history shows (module docstring)."""
        history = np.array(self._histories[opponent.name])
        on_current = np.full(len(s_m), opponent.e_y_m)
        on_racing = (
            np.asarray(self.racing_line.offset_at(s_m % self.track.length_m)) + history[-1, 1]
        )
        if len(history) < (self._histories[opponent.name].maxlen or 0):
            low, high = np.minimum(on_current, on_racing), np.maximum(on_current, on_racing)
        else:
            keeps_centre_offset = history[:, 0].std() <= history[:, 1].std()
            low = high = on_current if keeps_centre_offset else on_racing
        return low - PREDICTION_MARGIN_M, high + PREDICTION_MARGIN_M

    def _lane_bounds(self, s_stage: np.ndarray, plan_x: np.ndarray):
        """The lane's bounds, moved to the passing side of each opponent beside the stage;
        also sets each stage's speed cap: the following speed of the opponents it is not
        yet bounded clear of."""
        upper, lower = super()._lane_bounds(s_stage, plan_x)
        times = self.settings.dt_s * np.arange(1, len(s_stage))
        self._stage_caps_mps = np.full(len(times), np.inf)
        lane_upper, lane_lower = upper.copy(), lower.copy()
        self._offset_targets = np.zeros(len(times))
        self._target_sides = np.zeros(len(times), dtype=int)
        travelled_m = np.minimum(s_stage[1:] - s_stage[0], self._ego_speed_mps * times)
        self._reachable_m = MOVE_OVER_SLOPE * travelled_m  # the plan's speeds are >= 0.5 m/s
        for plan in self._passes:
            opponent, side = plan.opponent, plan.side
            s_opponent = opponent.s_m + opponent.v_mps * times
            gaps = wrap_arc(s_opponent - s_stage[1:], self.track.length_m)
            # once within reach, every stage until past it: dropping back frees none
            reach_m = PASS_LENGTH_M + LEAD_IN_M
            started = wrap_arc(opponent.s_m - s_stage[0], self.track.length_m) < reach_m
            beside = (gaps > -PASS_LENGTH_M) & ((gaps < reach_m) | started)
            held = gaps > -PASS_LENGTH_M  # the stages it follows the opponent in
            band_low, band_high = self.predicted_band(opponent, s_opponent[beside])
            reachable = self._reachable_m[beside]  # how far over the car can have moved
            falling_in = self.falling_in_from(opponent.name)
            if side > 0:
                clear = band_high + PASS_WIDTH_M
                wanted = np.minimum(clear, self._ego_e_y + reachable)
                lower[beside] = np.maximum(lower[beside], wanted)
                middle = 0.5 * (np.maximum(clear, lane_lower[beside]) + lane_upper[beside])
                self._offset_targets[beside] = np.minimum(middle, self._ego_e_y + reachable)
                self._target_sides[beside] = side
            elif side < 0:
                clear = band_low - PASS_WIDTH_M
                wanted = np.maximum(clear, self._ego_e_y - reachable)
                upper[beside] = np.minimum(upper[beside], wanted)
                middle = 0.5 * (np.minimum(clear, lane_upper[beside]) + lane_lower[beside])
                self._offset_targets[beside] = np.maximum(middle, self._ego_e_y - reachable)
                self._target_sides[beside] = side
            elif falling_in > 0:  # back behind it from the left, as gently as it moved over
                lower[beside] = np.maximum(lower[beside], self._ego_e_y - reachable)
            elif falling_in < 0:
                upper[beside] = np.minimum(upper[beside], self._ego_e_y + reachable)
            if side and not plan.follows:
                held[beside] = wanted != clear
            self._stage_caps_mps[held] = np.minimum(self._stage_caps_mps[held], plan.cap_mps)
        return upper, lower

    def _offset_reference(self, s_ref: np.ndarray) -> np.ndarray:
        """The reference line's offset, but beside an opponent the middle of the room on the
        passing side, where the reference line is nearer the opponent than that; and back to
        the line no steeper than ``MOVE_OVER_SLOPE`` (after a pass: no swerve)."""
        offsets = super()._offset_reference(s_ref)
        targets, sides = self._offset_targets, self._target_sides
        further = np.where(sides > 0, np.maximum(offsets, targets), np.minimum(offsets, targets))
        offsets = np.where(sides == 0, offsets, further)
        return np.clip(
            offsets, self._ego_e_y - self._reachable_m, self._ego_e_y + self._reachable_m
        )

    def _speed_caps_mps(self, s_m: np.ndarray, states: np.ndarray) -> np.ndarray:
        return self._stage_caps_mps


@dataclass(frozen=True)
class PassPlan:
    """What the ego does about one opponent this step: the side it keeps to (+1 left, -1
    right, 0 none), the speed that follows it (inf for a car it is level with or ahead of),
    and whether it follows (that speed holds on every stage: no side, or no room on its
    side) or only until the bounds clear the car."""

    opponent: NearOpponent
    side: int
    cap_mps: float
    follows: bool


@dataclass(frozen=True)
class NearOpponent:
    """An opponent within reach: its name, arc length, lateral offset and speed along the
    track, and whether it leaves room to a car alongside it (``info``'s ``leaves_room``)."""

    name: str
    s_m: float
    e_y_m: float
    v_mps: float
    leaves_room: bool = False


def opponents_near(opponents) -> list[NearOpponent]:
    """The opponents in ``info["opponents"]`` within reach of the ego."""
    near = []
    for opponent in opponents:
        if -LOOK_BEHIND_M < opponent["gap_m"] < LOOK_AHEAD_M:
            v_o = opponent["speed_mps"] * float(np.cos(opponent["e_psi_rad"]))
            leaves_room = bool(opponent.get("leaves_room", False))
            near.append(
                NearOpponent(opponent["name"], opponent["s_m"], opponent["e_y_m"], v_o, leaves_room)
            )
    return near


def following_speed_mps(gap_m: float, opponent: NearOpponent) -> float:
    """The fastest the ego may go ``gap_m`` behind ``opponent``: to stop ``FOLLOW_GAP_M``
    behind it when both brake at ``FOLLOW_BRAKING_MPS2``; closer, slower than it, to drop
    back at ``FALL_BACK_PER_S`` times the shortfall."""
    v_o = max(opponent.v_mps, 0.0)
    closable_m = gap_m - FOLLOW_GAP_M
    if closable_m < 0.0:
        return max(v_o + FALL_BACK_PER_S * closable_m, 0.0)
    return float(np.sqrt(v_o**2 + 2.0 * FOLLOW_BRAKING_MPS2 * closable_m))


def passing_side(ego_offset_m: float, left_room_m: float, right_room_m: float) -> int:
    """+1 to pass on the left, -1 on the right, 0 to follow: the side the ego is on if it
    has room, else the other if that has."""
    sides = [(1, left_room_m), (-1, right_room_m)]
    if ego_offset_m < 0.0:
        sides.reverse()
    for side, room in sides:
        if room >= 0.0:
            return side
    return 0
