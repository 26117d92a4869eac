"""Opponent drivers: the other cars of a race, each driven from ground truth and seeded.

- ``expert``: the expert MPC on the racing line at ``speed_factor`` of its speed profile,
  blind to the other cars.
- ``racer``: the traffic expert (:mod:`saferace.agents.traffic_expert`) at ``speed_factor``:
  it passes and follows the other cars, and leaves a car alongside it room, as racing rules
  ask (the fault rule blames a car that moves across into one alongside); its ``info``
  says so (``leaves_room``).
- ``pure-pursuit``: pure pursuit at a fixed ``lateral_offset_m`` from the centre line.
- ``lane-changer``: pure pursuit that switches between the lanes at ``+-lateral_offset_m``
  after seeded intervals, as AWS DeepRacer's head-to-bot cars do.
- ``blocker``: pure pursuit that covers the inside of the next turn, and the line of a car
  close behind it.
- ``braking``: pure pursuit on the racing line that brakes as hard as it can at seeded times.

Each gets ``reset(rng)`` at the env's reset, from the env's seeded generator.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from saferace.agents.mpc import MPCExpert
from saferace.agents.pure_pursuit import PurePursuit, PurePursuitSettings
from saferace.agents.traffic_expert import TrafficExpert
from saferace.envs.reference_lines import reference_line
from saferace.envs.traffic import OpponentSpec
from saferace.safety.ltv_mpc import MPCSettings
from saferace.track.frenet import wrap_arc

#: How far from the lane's edge an opponent's target line stays (m), beyond its half width.
EDGE_MARGIN_M = 0.05
#: How fast an opponent's target line moves sideways (m/s).
LINE_CHANGE_MPS = 0.5
#: The lane changer's time in a lane, and the braking car's time between stops (s).
LANE_TIME_S = (3.0, 8.0)
BRAKING_INTERVAL_S = (4.0, 8.0)
BRAKING_DURATION_S = 1.2
#: The blocker covers a car behind it closer than this (m), else the next turn's inside,
#: looked for this far ahead (m).
BLOCK_RANGE_M = 4.0
TURN_LOOKAHEAD_M = 3.0


class _Restorable:
    """``get_state``/``set_state`` of the attributes that change while driving (pickling an
    env saves its opponents' drivers by them)."""

    state_attributes: tuple[str, ...] = ()

    def get_state(self) -> dict[str, Any]:
        return {name: copy.deepcopy(getattr(self, name)) for name in self.state_attributes}

    def set_state(self, state: dict[str, Any]) -> None:
        for name, value in state.items():
            setattr(self, name, copy.deepcopy(value))


class OffsetPursuit(_Restorable, PurePursuit):
    """Pure pursuit of a line at a lateral offset from the centre line that the subclass
    chooses (:meth:`wanted_offset_m`), moved toward it at ``LINE_CHANGE_MPS``."""

    state_attributes: tuple[str, ...] = ("offset_m", "rng")

    def __init__(self, env, spec: OpponentSpec) -> None:
        base = env.unwrapped
        settings = PurePursuitSettings(speed_scale=spec.speed_factor, max_speed_mps=8.0)
        super().__init__(base.track, reference_line(base.track, "center"), settings)
        self.spec = spec
        self.dt_s = base.control_dt_s
        self.half_width_m = base.car_half_width_m
        self.offset_m = spec.lateral_offset_m
        self.rng = np.random.default_rng(0)

    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.offset_m = self.spec.lateral_offset_m

    def act(self, observation: Any, info: dict[str, Any]) -> np.ndarray:
        step = LINE_CHANGE_MPS * self.dt_s
        wanted = self.wanted_offset_m(info)
        self.offset_m += float(np.clip(wanted - self.offset_m, -step, step))
        return super().act(observation, info)

    def wanted_offset_m(self, info: dict[str, Any]) -> float:
        return self.spec.lateral_offset_m

    def target_offset_m(self, s_m: float, info: dict[str, Any]) -> float:
        """The current offset, kept ``EDGE_MARGIN_M`` inside the lane at ``s_m`` and, on the
        inside of a turn, what pure pursuit cuts off it more (``L^2 kappa / 2`` for a
        look-ahead ``L``)."""
        w_right, w_left = (float(w) for w in self.track.widths(s_m))
        lookahead = wrap_arc(s_m - info["s_m"], self.track.length_m)
        kappa = float(self.track.centerline.curvature_scalar(info["s_m"] + 0.5 * lookahead))
        cut = 0.5 * lookahead * lookahead * kappa  # toward the turn's centre: left if positive
        room = self.half_width_m + EDGE_MARGIN_M
        high = w_left - room - max(cut, 0.0)
        low = room - w_right + max(-cut, 0.0)
        return float(np.clip(self.offset_m, min(low, 0.0), max(high, 0.0)))


class LaneChanger(OffsetPursuit):
    """Switches between the lanes at ``+-lateral_offset_m`` after seeded intervals."""

    state_attributes: tuple[str, ...] = ("offset_m", "rng", "side", "switch_time_s")

    def reset(self, rng: np.random.Generator) -> None:
        super().reset(rng)
        self.side = 1.0
        self.switch_time_s = float(rng.uniform(*LANE_TIME_S))

    def wanted_offset_m(self, info: dict[str, Any]) -> float:
        if info["time_s"] >= self.switch_time_s:
            self.side = -self.side
            self.switch_time_s = info["time_s"] + float(self.rng.uniform(*LANE_TIME_S))
        return self.side * abs(self.spec.lateral_offset_m)


class Blocker(OffsetPursuit):
    """Covers the line of the closest car behind it within ``BLOCK_RANGE_M``, else the
    inside of the turn ``TURN_LOOKAHEAD_M`` ahead, within ``+-lateral_offset_m``."""

    def wanted_offset_m(self, info: dict[str, Any]) -> float:
        cover = abs(self.spec.lateral_offset_m)
        length = self.track.length_m
        behind = [
            (wrap_arc(info["s_m"] - other["s_m"], length), other["e_y_m"])
            for other in info.get("cars", ())
        ]
        chasers = [(gap, e_y) for gap, e_y in behind if 0.0 < gap < BLOCK_RANGE_M]
        if chasers:
            return float(np.clip(min(chasers)[1], -cover, cover))
        kappa = float(self.track.centerline.curvature_scalar(info["s_m"] + TURN_LOOKAHEAD_M))
        return float(np.sign(kappa)) * cover


class BrakingCar(_Restorable, PurePursuit):
    """Pure pursuit of the racing line that brakes as hard as it can for
    ``BRAKING_DURATION_S`` at seeded intervals."""

    state_attributes: tuple[str, ...] = ("brake_at_s", "rng")

    def __init__(self, env, spec: OpponentSpec) -> None:
        base = env.unwrapped
        settings = PurePursuitSettings(speed_scale=spec.speed_factor, max_speed_mps=8.0)
        super().__init__(base.track, reference_line(base.track, "racing"), settings)
        self.max_brake_mps2 = base.params.max_brake_mps2
        self.brake_at_s = float(np.mean(BRAKING_INTERVAL_S))
        self.rng = np.random.default_rng(0)

    def reset(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.brake_at_s = float(rng.uniform(*BRAKING_INTERVAL_S))

    def act(self, observation: Any, info: dict[str, Any]) -> np.ndarray:
        action = super().act(observation, info)
        time_s = info["time_s"]
        if time_s >= self.brake_at_s + BRAKING_DURATION_S:
            self.brake_at_s = time_s + float(self.rng.uniform(*BRAKING_INTERVAL_S))
        if time_s >= self.brake_at_s:
            action[1] = -self.max_brake_mps2
        return action


class ExpertOpponent(_Restorable, MPCExpert):
    """The expert MPC on the racing line at the spec's speed factor. Its state is its last
    plan; its QP solver's warm start is not part of it, so a restored expert's next plans
    agree with the original's to the solver's tolerance, not to the bit."""

    state_attributes: tuple[str, ...] = ("_plan_x", "_plan_slack", "_plan_u", "_previous_u", "_x0")

    def reset(self, rng: np.random.Generator | None = None) -> None:
        """Forget the last plan and the solver's warm start: an episode is the same for
        the same seed."""
        super().reset()
        self._solver = None


class RacerOpponent(ExpertOpponent, TrafficExpert):
    """The traffic expert on the racing line at the spec's speed factor: it passes and
    follows the other cars as the ego's expert does, and keeps its side of a car alongside
    it (within ``PASS_LENGTH_M`` behind), so it leaves that car room. Reset and restored as
    :class:`ExpertOpponent` is, with the cars it remembers; it forgets them at an episode's
    first step (:meth:`TrafficExpert.act`), not at a reset, which the MPC also calls after
    a failed solve."""

    leaves_room = True
    state_attributes: tuple[str, ...] = (
        *ExpertOpponent.state_attributes,
        "_histories",
        "_sides",
        "_given_up",
    )

    def act(self, observation: Any, info: dict[str, Any]) -> np.ndarray:
        """The traffic expert's action, the other cars (``info["cars"]``) its opponents."""
        length = self.track.length_m
        others = [
            other | {"gap_m": wrap_arc(other["s_m"] - info["s_m"], length)}
            for other in info.get("cars", ())
        ]
        return super().act(observation, info | {"opponents": others})


def make_opponent(spec: OpponentSpec, env) -> Any:
    """The driver of an opponent ``spec`` in ``env``."""
    base = env.unwrapped
    if spec.policy in ("expert", "racer"):
        driver = ExpertOpponent if spec.policy == "expert" else RacerOpponent
        settings = MPCSettings(dt_s=base.control_dt_s, speed_scale=spec.speed_factor)
        racing = reference_line(base.track, "racing")
        return driver(base.track, racing, settings=settings, drivetrain=base.params)
    if spec.policy == "pure-pursuit":
        return OffsetPursuit(env, spec)
    if spec.policy == "lane-changer":
        return LaneChanger(env, spec)
    if spec.policy == "blocker":
        return Blocker(env, spec)
    if spec.policy == "braking":
        return BrakingCar(env, spec)
    raise ValueError(f"no driver for opponent policy {spec.policy!r}")
