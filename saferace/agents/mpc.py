"""Expert MPC: the LTV MPC of :mod:`saferace.safety.ltv_mpc` tracking the task's reference
line from the ground truth in ``info`` (the plan's cost on the reference's offset, heading
and speed; its lane bounds with a margin).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from saferace.safety.ltv_mpc import FrenetMPC, MPCSettings

#: The expert's target-speed label: its plan's speed this far ahead (s). A speed loop with
#: ``kp = 1 / lookahead`` tracking it asks for the plan's mean acceleration over that time
#: (:class:`saferace.agents.pid.PIDGains`).
TARGET_SPEED_LOOKAHEAD_S = 0.25


class MPCExpert(FrenetMPC):
    """The expert driver; ``act(obs, info) -> [steer_rad, accel_mps2]`` from ground truth."""

    @classmethod
    def for_env(cls, env, model: str = "dynamic", settings: MPCSettings | None = None) -> MPCExpert:
        """An expert for a (possibly wrapped) SafeRace env's track and reference line."""
        base = env.unwrapped
        settings = settings or MPCSettings(dt_s=base.control_dt_s)
        return cls(
            base.track, base.reference, model=model, settings=settings, drivetrain=base.params
        )

    # ------------------------------------------------------------------ acting
    def act(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        start = time.perf_counter()
        x0 = self.state_from_info(info)
        if info.get("time_s", 0.0) == 0.0 or self._plan_x is None:
            self.reset()
        self._previous_u[0] = info.get("steer_rad", self._previous_u[0])
        u = self._solve(x0, info["s_m"])
        self._previous_u = u
        self._x0 = x0
        self.stats.step_times_s.append(time.perf_counter() - start)
        return np.array([u[0], self._accel_command(u[1], info["v_x_mps"])], dtype=np.float32)

    def planned_speed_mps(self, lookahead_s: float = TARGET_SPEED_LOOKAHEAD_S) -> float:
        """The speed the last plan reaches ``lookahead_s`` ahead (call after :meth:`act`).

        After a failed solve (no plan) it is the speed the applied acceleration reaches.
        """
        step = min(max(round(lookahead_s / self.settings.dt_s), 1), self.settings.horizon)
        index = self.model.speed_index
        if self._plan_x is None:
            return float(self._x0[index] + self._previous_u[1] * step * self.settings.dt_s)
        return float(self._plan_x[step, index])

    def state_from_info(self, info: dict[str, Any]) -> np.ndarray:
        """The plan's state from the env's ground truth: the model's, then the wheels' angle."""
        state = self.model.state_from(
            info["e_y_m"],
            info["e_psi_rad"],
            info["v_x_mps"],
            info["v_y_mps"],
            info["yaw_rate_radps"],
        )
        return np.append(state, info["steer_angle_rad"])

    def _accel_command(self, accel_mps2: float, speed_mps: float) -> float:
        """The command that realises ``accel_mps2`` given the identified gain and drag."""
        return (accel_mps2 + self.params.drag_per_s * speed_mps) / self.params.accel_gain
