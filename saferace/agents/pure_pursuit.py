"""Pure pursuit on the task's reference line, from the ground truth in ``info``.

A baseline driver and the simulator's smoke test: it steers toward the point of the
reference line ``lookahead_m`` ahead along the track, and tracks a fraction of the
reference speed with a proportional speed loop, braking early enough for slower
reference speeds ahead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from saferace.track import Track
from saferace.track.raceline import ReferenceLine


@dataclass(frozen=True)
class PurePursuitSettings:
    """Look-ahead, speed and gains of the pure-pursuit driver."""

    lookahead_m: float = 0.6
    lookahead_per_speed_s: float = 0.15
    speed_scale: float = 0.7
    max_speed_mps: float = 4.0
    speed_gain_per_s: float = 2.0
    planning_decel_mps2: float = 2.5
    wheelbase_m: float = 0.33


class PurePursuit:
    """Steer toward a look-ahead point on the reference line; ``act(obs, info) -> action``."""

    def __init__(
        self, track: Track, reference: ReferenceLine, settings: PurePursuitSettings | None = None
    ):
        self.track = track
        self.reference = reference
        self.settings = settings or PurePursuitSettings()

    @classmethod
    def for_env(cls, env, settings: PurePursuitSettings | None = None) -> PurePursuit:
        """A driver for a (possibly wrapped) SafeRace env's track and reference line."""
        base = env.unwrapped
        return cls(base.track, base.reference, settings)

    def act(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        settings = self.settings
        speed = info["v_x_mps"]
        lookahead = settings.lookahead_m + settings.lookahead_per_speed_s * max(speed, 0.0)
        s_target = info["s_m"] + lookahead
        center = self.track.centerline
        offset = self.target_offset_m(s_target, info)
        target = center.position(s_target) + offset * center.normal(s_target)
        dx, dy = target[0] - info["x_m"], target[1] - info["y_m"]
        yaw = info["yaw_rad"]
        local_x = math.cos(yaw) * dx + math.sin(yaw) * dy
        local_y = -math.sin(yaw) * dx + math.cos(yaw) * dy
        distance_sq = local_x * local_x + local_y * local_y
        steer = math.atan(2.0 * settings.wheelbase_m * local_y / max(distance_sq, 1e-6))
        accel = settings.speed_gain_per_s * (self.target_speed(info["s_m"], speed) - speed)
        return np.array([steer, accel], dtype=np.float32)

    def target_offset_m(self, s_m: float, info: dict[str, Any]) -> float:
        """The lateral offset (m, positive left) of the point steered to at ``s_m``: the
        reference line's (drivers that leave it override this)."""
        return float(self.reference.offset_at(s_m))

    def target_speed(self, s_m: float, speed_mps: float) -> float:
        """The fastest speed now from which every scaled reference speed ahead can be reached."""
        settings = self.settings
        decel = settings.planning_decel_mps2
        horizon = max(speed_mps, 0.0) ** 2 / (2.0 * decel) + 0.5
        ahead = np.linspace(0.0, horizon, 12)
        allowed = settings.speed_scale * self.reference.speed_at(s_m + ahead)
        now = np.sqrt(allowed**2 + 2.0 * decel * ahead)
        return float(min(settings.max_speed_mps, now.min()))
