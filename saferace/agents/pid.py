"""PID speed controller: a target speed in, an acceleration command out (paper Sec. 2.4).

The learned control network outputs a target speed rather than a throttle; this loop turns
it into the task's ``accel_mps2``, as the paper's RC car and CARLA agents did. The integral
term holds speed against drag; it is frozen while the command saturates (anti-windup).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PIDGains:
    """Gains of the speed loop and the command's limits (the task's action bounds).

    ``kp_per_s = 4``: the expert's target speed is its plan's speed 0.25 s ahead
    (:data:`saferace.agents.mpc.TARGET_SPEED_LOOKAHEAD_S`), so ``kp = 1 / 0.25 s`` asks for
    the plan's mean acceleration over that time.
    """

    kp_per_s: float = 4.0
    ki_per_s2: float = 1.0
    kd: float = 0.0
    min_accel_mps2: float = -4.0
    max_accel_mps2: float = 4.0

    def __post_init__(self) -> None:
        if min(self.kp_per_s, self.ki_per_s2, self.kd) < 0.0:
            raise ValueError(f"PID gains must not be negative, got {self}")
        if not self.min_accel_mps2 < self.max_accel_mps2:
            raise ValueError(
                f"need min_accel_mps2 < max_accel_mps2, got "
                f"{self.min_accel_mps2} and {self.max_accel_mps2}"
            )


class PIDSpeedController:
    """``command(target_speed, speed) -> accel_mps2`` at a fixed control period."""

    def __init__(self, dt_s: float, gains: PIDGains | None = None) -> None:
        if dt_s <= 0.0:
            raise ValueError(f"dt_s must be positive, got {dt_s}")
        self.dt_s = dt_s
        self.gains = gains or PIDGains()
        self.reset()

    def reset(self) -> None:
        """Forget the integral and the last error (call at the start of an episode)."""
        self._integral = 0.0
        self._last_error: float | None = None

    def command(self, target_speed_mps: float, speed_mps: float) -> float:
        """The acceleration command (m/s^2) that drives ``speed_mps`` to the target."""
        gains = self.gains
        error = float(target_speed_mps) - float(speed_mps)
        derivative = 0.0 if self._last_error is None else (error - self._last_error) / self.dt_s
        self._last_error = error
        integral = self._integral + error * self.dt_s
        raw = gains.kp_per_s * error + gains.ki_per_s2 * integral + gains.kd * derivative
        command = min(gains.max_accel_mps2, max(gains.min_accel_mps2, raw))
        if command == raw:  # anti-windup: integrate only while the command is not saturated
            self._integral = integral
        return command
