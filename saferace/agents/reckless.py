"""Reckless test agents: drivers that leave the lane, to show what the safety filter does.

All hold a target speed with a proportional loop on ``info["v_x_mps"]``:

- :class:`DriftAgent` steers a constant angle, drifting toward one boundary.
- :class:`WeaveAgent` weaves with large sinusoidal steering.
- :class:`SpeedingAgent` follows the task's reference (the racing line on
  ``RacingLine-v0``) by pure pursuit at a multiple of its speed profile.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from saferace.agents.pure_pursuit import PurePursuit, PurePursuitSettings

SPEED_GAIN_PER_S = 2.0


@dataclass
class _SteeringPattern:
    """A steering pattern in time at a constant target speed; subclasses give the steering."""

    speed_mps: float = 3.0

    @classmethod
    def for_env(cls, env) -> _SteeringPattern:
        return cls()

    def steer_rad(self, time_s: float) -> float:
        raise NotImplementedError

    def act(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        accel = SPEED_GAIN_PER_S * (self.speed_mps - info["v_x_mps"])
        return np.array([self.steer_rad(info["time_s"]), accel], np.float32)


@dataclass
class DriftAgent(_SteeringPattern):
    """Constant steering (rad, positive left) at a constant target speed."""

    steer_angle_rad: float = 0.1

    def steer_rad(self, time_s: float) -> float:
        return self.steer_angle_rad


@dataclass
class WeaveAgent(_SteeringPattern):
    """Steering ``amplitude * sin(2 pi t / period)`` at a constant target speed."""

    amplitude_rad: float = 0.3
    period_s: float = 2.0

    def steer_rad(self, time_s: float) -> float:
        return self.amplitude_rad * math.sin(2.0 * math.pi * time_s / self.period_s)


class SpeedingAgent(PurePursuit):
    """Pure pursuit of the task's reference line at ``speed_factor`` times its speed profile."""

    @classmethod
    def for_env(
        cls, env, settings: PurePursuitSettings | None = None, speed_factor: float = 1.6
    ) -> SpeedingAgent:
        """Pure pursuit at ``speed_factor`` times the speed profile (at most 8 m/s), unless
        ``settings`` say otherwise."""
        settings = settings or PurePursuitSettings(speed_scale=speed_factor, max_speed_mps=8.0)
        base = env.unwrapped
        return cls(base.track, base.reference, settings)


RECKLESS_AGENTS: dict[str, type[_SteeringPattern] | type[SpeedingAgent]] = {
    "drift": DriftAgent,
    "weave": WeaveAgent,
    "speeding": SpeedingAgent,
}
