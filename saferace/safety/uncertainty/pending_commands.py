"""Commands sent but perhaps not applied yet, for a car whose actuators may act up to
``max_delay_steps`` control steps late: the lane states a new command may meet.

A command sent now acts after the commands still in the pipe. With a delay of ``k`` steps
those are the last ``k`` commands sent, so the lane state the new command meets is the
present one carried through them by the kinematic bicycle in Frenet coordinates: the
robust filter certifies there (a predictor, as Smith's for delayed loops). The bound of the
delay is declared, as a car's datasheet gives its actuation latency
(:data:`~saferace.names.ACTUATION_DELAY_ATTRIBUTE`, as the odometry's error is declared);
the delay itself is judged online from the yaw rate
(:class:`~saferace.safety.uncertainty.steering_trim.SteeringTrim`), which takes half a
second of steering to tell. So the filter certifies over every delay from the one judged to
the bound: all of them until the yaw rate has told (a delay that sets in finds the filter
ready), then the judged one alone where it is the bound. On 120 drives under delays of 1-3
steps on three circuits the filter left 1 run 0.1 s outside this way; certifying at the
judged delay alone, 2 (the delay's onset, on a narrow lane); over every delay always, 2 for
up to 5.6 s (the present state mixed into a late command's). Without a declared delay
nothing changes.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Callable

import gymnasium as gym
import numpy as np

from saferace.faults.wrapper import declared
from saferace.names import ACTUATION_DELAY_ATTRIBUTE
from saferace.safety.uncertainty.estimate import StateEstimate


class PendingCommands:
    """The last ``max_delay_steps`` commands sent (steering as the wheels take it, in rad,
    and acceleration, m/s^2) and where they carry a box of lane states."""

    def __init__(
        self,
        max_delay_steps: int,
        control_dt_s: float,
        wheelbase_m: float,
        curvature_at: Callable[[float], float],
    ) -> None:
        if max_delay_steps < 0:
            raise ValueError(f"max_delay_steps must be >= 0, got {max_delay_steps}")
        self.max_delay_steps = max_delay_steps
        self.control_dt_s = control_dt_s
        self.wheelbase_m = wheelbase_m
        self.curvature_at = curvature_at  # the map's, at the centre line's s
        self.sent: deque[tuple[float, float]] = deque(maxlen=max(max_delay_steps, 1))

    @classmethod
    def of_task(cls, env: gym.Env, control_dt_s: float, wheelbase_m: float) -> PendingCommands:
        """The pipe of ``env``'s actuators, as long as its wrappers declare (none: the
        simulator's, which applies every command at once), on its track."""
        steps = int(declared(env, ACTUATION_DELAY_ATTRIBUTE))
        track = env.unwrapped.track  # type: ignore[attr-defined]  # a SafeRace task
        return cls(steps, control_dt_s, wheelbase_m, track.centerline.curvature_scalar)

    def reset(self) -> None:
        self.sent.clear()

    def record(self, steer_rad: float, accel_mps2: float) -> None:
        """A command sent this step."""
        if self.max_delay_steps:
            self.sent.append((steer_rad, accel_mps2))

    def meet(
        self,
        estimate: StateEstimate,
        velocity: np.ndarray,
        s_m: float,
        delay_steps: int,
    ) -> tuple[StateEstimate, np.ndarray, float]:
        """The state a command sent now meets, from ``s_m`` at ``velocity``
        (``[v_x, v_y, r]``): over every delay from ``delay_steps`` (the one judged) to the
        bound, the box of ``estimate`` carried through as many of the last commands sent
        (its corners, and their hull), the curvatures of the map there, the fastest speed;
        where the judged delay takes it."""
        sent = list(self.sent)
        if not sent:
            return estimate, velocity, s_m
        lower, upper, speed_mps = estimate.lower, estimate.upper, float(velocity[0])
        corners = np.array(
            [(e_y, e_psi) for e_y in (lower[0], upper[0]) for e_psi in (lower[1], upper[1])]
        )
        reached = [
            self._carried(corners, sent[len(sent) - delay :], speed_mps, s_m)
            for delay in range(min(delay_steps, len(sent)), len(sent) + 1)
        ]
        points = np.vstack([points for points, _, _ in reached])
        curvatures = [self.curvature_at(s_ahead) for _, s_ahead, _ in reached]
        low = np.array([*points.min(axis=0), min(curvatures)])
        high = np.array([*points.max(axis=0), max(curvatures)])
        velocity = np.array([max(speed for _, _, speed in reached), *velocity[1:]], dtype=float)
        return dataclasses.replace(estimate, lower=low, upper=high), velocity, reached[0][1]

    def _carried(
        self,
        corners: np.ndarray,
        commands: list[tuple[float, float]],
        speed_mps: float,
        s_m: float,
    ) -> tuple[np.ndarray, float, float]:
        """The corners carried through ``commands`` (none: where they are); the centre
        line's ``s`` and the speed then."""
        e_y, e_psi = corners[:, 0].copy(), corners[:, 1].copy()
        dt = self.control_dt_s
        s = np.full(len(corners), s_m)
        speed = speed_mps
        for steer_rad, accel_mps2 in commands:
            kappa = np.array([self.curvature_at(float(value)) for value in s])
            along = speed * np.cos(e_psi) / np.maximum(1.0 - kappa * e_y, 0.1)
            yaw_rate = speed * math.tan(steer_rad) / self.wheelbase_m
            e_y = e_y + speed * np.sin(e_psi) * dt
            e_psi = e_psi + (yaw_rate - kappa * along) * dt
            s = s + along * dt
            speed = max(0.0, speed + accel_mps2 * dt)
        return np.column_stack([e_y, e_psi]), float(s.mean()), speed
