"""Sensor and actuator faults as a gymnasium wrapper, and as the tasks' ``faults`` argument.

``SensorFaults(env, ["blackout:start=3,duration=2", "latency:steps=2"])`` gives the
driver (and any filter behind it) the faulty frames and velocities, and applies its
commands through the faulty actuators (:mod:`.spec`, :mod:`.inject`).
``gym.make("saferace/CenterLine-v0", faults=[...])`` is the same task wrapped. ``info``
says which faults act (``faults``, by name) and what the actuators applied
(``applied_action``): for tables and plots, never for the agent or the filter. It also
gives the pose the car's odometry integrated from the start, faulty where the odometry
is (:data:`~saferace.names.ODOMETRY_POSE_KEY`): what a filter carries its set by.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import gymnasium as gym
import numpy as np

from saferace.faults.inject import FaultInjector
from saferace.faults.spec import Fault, parse_faults
from saferace.names import ODOMETRY_POSE_KEY
from saferace.track.odometry import moved_by, odometry_step


class SensorFaults(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """``env`` with ``faults`` (strings ``NAME[:KEY=VALUE,...]`` or :class:`Fault`)."""

    def __init__(self, env: gym.Env, faults: Iterable[str | Fault] | str) -> None:
        self.faults = parse_faults(faults)
        gym.utils.RecordConstructorArgs.__init__(
            self, faults=[fault.spec() for fault in self.faults]
        )
        super().__init__(env)
        self.injector = FaultInjector(
            self.faults,
            env.action_space.low,  # type: ignore[attr-defined]
            env.action_space.high,  # type: ignore[attr-defined]
        )
        odometry = next((fault for fault in self.faults if fault.name == "odometry"), None)
        #: How far off, as a fraction, the odometry may measure distance and turn: its
        #: fault's bias (:data:`~saferace.names.ODOMETRY_ERROR_ATTRIBUTE`), from the start.
        self.odometry_scale_error = 0.0 if odometry is None else abs(float(odometry["bias"]))
        delay = next((fault for fault in self.faults if fault.name == "delay"), None)
        #: The most control steps the actuators may apply a command late: the delay fault's
        #: (:data:`~saferace.names.ACTUATION_DELAY_ATTRIBUTE`), from the start.
        self.actuation_delay_steps = 0 if delay is None else int(delay["steps"])
        latency = next((fault for fault in self.faults if fault.name == "latency"), None)
        #: The most control steps the camera's frames may arrive late: the latency fault's
        #: (:data:`~saferace.names.CAMERA_LATENCY_ATTRIBUTE`), from the start.
        self.camera_latency_steps = 0 if latency is None else int(latency["steps"])
        self._time_s = 0.0
        self._seeded = False
        self._true_pose = self._odometry_pose = np.zeros(3)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        observation, info = self.env.reset(seed=seed, options=options)
        if seed is None and self._seeded:  # the next episode of the seeded sequence
            seed = int(self.injector.rng.integers(2**31))
        self.injector.reset(seed)
        self._seeded = self._seeded or seed is not None
        self._odometry_pose = true_pose(info)
        return self._faulty(observation, info)

    def step(self, action: np.ndarray):  # type: ignore[no-untyped-def]  # gym.Wrapper's
        applied = self.injector.command(action, self._time_s)
        observation, reward, terminated, truncated, info = self.env.step(applied)
        info["applied_action"] = applied
        observation, info = self._faulty(observation, info, stepped=True)
        return observation, reward, terminated, truncated, info

    def _faulty(
        self, observation: dict[str, np.ndarray], info: dict[str, Any], stepped: bool = False
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """The faulty sensors' observation and ``info`` of a reset, or of a step (``stepped``:
        the odometry carried over it)."""
        time_s = float(info["time_s"])
        observation = {
            **observation,
            "image": self.injector.frame(observation["image"], time_s),
            "velocity": self.injector.velocity(observation["velocity"], time_s),
        }
        pose = true_pose(info)
        if stepped:
            step = odometry_step(self._true_pose, pose)
            measured = self.injector.odometry(step, time_s - self._time_s, time_s)
            self._odometry_pose = moved_by(self._odometry_pose, measured)
        self._true_pose, self._time_s = pose, time_s
        info["faults"] = self.injector.active(self._time_s)
        info[ODOMETRY_POSE_KEY] = self._odometry_pose.copy()
        return observation, info


def true_pose(info: dict[str, Any]) -> np.ndarray:
    """``(x, y, yaw)`` of the car in ``info``: the simulator's."""
    return np.array([info["x_m"], info["y_m"], info["yaw_rad"]], dtype=float)


def declared(env: gym.Env, name: str) -> float:
    """What ``env``'s wrappers declare of its sensors and actuators under ``name`` (the
    datasheet values :data:`~saferace.names.ODOMETRY_ERROR_ATTRIBUTE`,
    :data:`~saferace.names.ACTUATION_DELAY_ATTRIBUTE` and
    :data:`~saferace.names.CAMERA_LATENCY_ATTRIBUTE`); 0 where none declares it: the
    simulator's sensors are exact, its frames on time and its actuators act at once."""
    return float(env.get_wrapper_attr(name)) if env.has_wrapper_attr(name) else 0.0


def with_faults(env: gym.Env, faults: Iterable[str | Fault] | str | None) -> gym.Env:
    """``env`` wrapped in :class:`SensorFaults` where ``faults`` names any."""
    parsed = parse_faults(faults)
    return SensorFaults(env, parsed) if parsed else env
