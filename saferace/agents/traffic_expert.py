"""The expert MPC in traffic: it plans around the opponents in ``info``, passing where the
lane has room and following where it has not.

Each opponent is predicted to go on along its current line at its speed along its
heading (``speed cos(e_psi)``; the filter's car barriers also divide by the Frenet
frame's stretch). At every stage of the plan where the ego car's predicted arc length is
within ``PASS_LENGTH_M`` of an opponent's, the opponent takes the band ``e_y_o
+- PASS_WIDTH_M`` of the lane: the stage's lateral bound moves to the side the car passes
on (the side it is on now if that has room, else the other; once alongside, its own
whatever the room: it never cuts across the opponent's nose), and the plan overtakes.
Where the side it may take has no room beside an opponent ahead, the plan follows: every
stage's speed is capped at the opponent's plus what closes the gap to ``FOLLOW_GAP_M`` in
``FOLLOW_TIME_S``. A car behind it is never followed (braking for it would only invite it
in). The bounds are soft, as the lane's are; the safety filter's car barriers are what
guarantee clearance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from saferace.agents.mpc import MPCExpert
from saferace.safety.car_barriers import BUMPER_HALF_LENGTH_M, BUMPER_HALF_WIDTH_M
from saferace.track.frenet import wrap_arc

#: Along the track, the ego is beside an opponent while their centres are this close (m):
#: a bumper's length plus a margin.
PASS_LENGTH_M = 2.0 * BUMPER_HALF_LENGTH_M + 0.3
#: Across it, the ego's centre keeps this far from the opponent's (m): a bumper's width plus
#: a margin.
PASS_WIDTH_M = 2.0 * BUMPER_HALF_WIDTH_M + 0.08
#: Following: the gap between centres it keeps (m), and how fast it closes a larger one (s).
FOLLOW_GAP_M = 1.0
FOLLOW_TIME_S = 1.0
#: Opponents further ahead than this (m) or behind are ignored.
LOOK_AHEAD_M = 12.0
LOOK_BEHIND_M = 1.0


class TrafficExpert(MPCExpert):
    """The expert MPC that passes or follows the opponents in ``info["opponents"]``."""

    speed_rows = True
    #: This step's opponents near the car (set by :meth:`act`), and those it follows
    #: ``(gap, v_o)`` (set with the plan's lane bounds, read by its caps).
    _opponents: list[NearOpponent] = []  # noqa: RUF012 - replaced, never mutated
    _follow: list[tuple[float, float]] = []  # noqa: RUF012 - replaced, never mutated

    def act(self, observation: Any, info: dict[str, Any]) -> np.ndarray:
        self._opponents = opponents_near(info.get("opponents", ()))
        self._ego_e_y = float(info["e_y_m"])
        return super().act(observation, info)

    def _lane_bounds(self, s_stage: np.ndarray, plan_x: np.ndarray):
        upper, lower = super()._lane_bounds(s_stage, plan_x)
        self._follow = []
        times = self.settings.dt_s * np.arange(1, len(s_stage))
        for opponent in self._opponents:
            gaps = wrap_arc(
                opponent.s_m + opponent.v_mps * times - s_stage[1:], self.track.length_m
            )
            beside = np.abs(gaps) < PASS_LENGTH_M
            if not beside.any():
                continue
            e_y_o = opponent.e_y_m
            left_room = upper[beside] - (e_y_o + PASS_WIDTH_M)
            right_room = (e_y_o - PASS_WIDTH_M) - lower[beside]
            offset = self._ego_e_y - opponent.e_y_m
            rooms = (left_room.min(), right_room.min())
            if abs(gaps[0]) < PASS_LENGTH_M:  # alongside: its own side, never across the nose
                side = 1 if offset > 0.0 else -1
                boxed = rooms[0 if side > 0 else 1] < 0.0
            else:
                side = passing_side(offset, *rooms)
                boxed = side == 0
            if side > 0:
                lower[beside] = np.maximum(lower[beside], e_y_o + PASS_WIDTH_M)
            elif side < 0:
                upper[beside] = np.minimum(upper[beside], e_y_o - PASS_WIDTH_M)
            if boxed and gaps[0] > 0.0:  # no room beside a car ahead: follow it
                self._follow.append((float(gaps[0]), opponent.v_mps))
        return upper, lower

    def _speed_caps_mps(self, s_m: np.ndarray, states: np.ndarray) -> np.ndarray:
        caps = np.full(len(s_m), np.inf)
        for gap, v_o in self._follow:
            caps[:] = np.minimum(caps, max(0.0, v_o + (gap - FOLLOW_GAP_M) / FOLLOW_TIME_S))
        return caps


@dataclass(frozen=True)
class NearOpponent:
    """An opponent within reach: its name, arc length, lateral offset and speed along the
    track."""

    name: str
    s_m: float
    e_y_m: float
    v_mps: float


def opponents_near(opponents) -> list[NearOpponent]:
    """The opponents in ``info["opponents"]`` within reach of the ego."""
    near = []
    for opponent in opponents:
        if -LOOK_BEHIND_M < opponent["gap_m"] < LOOK_AHEAD_M:
            v_o = opponent["speed_mps"] * float(np.cos(opponent["e_psi_rad"]))
            near.append(NearOpponent(opponent["name"], opponent["s_m"], opponent["e_y_m"], v_o))
    return near


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
