"""Sensor and actuator faults as a gymnasium wrapper, and as the tasks' ``faults`` argument.

``SensorFaults(env, ["blackout:start=3,duration=2", "latency:steps=2"])`` gives the
driver (and any filter behind it) the faulty frames and velocities, and applies its
commands through the faulty actuators (:mod:`.spec`, :mod:`.inject`).
``gym.make("saferace/CenterLine-v0", faults=[...])`` is the same task wrapped. ``info``
says which faults act (``faults``, by name) and what the actuators applied
(``applied_action``): for tables and plots, never for the agent or the filter.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import gymnasium as gym
import numpy as np

from saferace.faults.inject import FaultInjector
from saferace.faults.spec import Fault, parse_faults


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
        self._time_s = 0.0
        self._seeded = False

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        observation, info = self.env.reset(seed=seed, options=options)
        if seed is None and self._seeded:  # the next episode of the seeded sequence
            seed = int(self.injector.rng.integers(2**31))
        self.injector.reset(seed)
        self._seeded = self._seeded or seed is not None
        return self._faulty(observation, info)

    def step(self, action: np.ndarray):  # type: ignore[no-untyped-def]  # gym.Wrapper's
        applied = self.injector.command(action, self._time_s)
        observation, reward, terminated, truncated, info = self.env.step(applied)
        info["applied_action"] = applied
        observation, info = self._faulty(observation, info)
        return observation, reward, terminated, truncated, info

    def _faulty(
        self, observation: dict[str, np.ndarray], info: dict[str, Any]
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        self._time_s = float(info["time_s"])
        observation = {
            **observation,
            "image": self.injector.frame(observation["image"], self._time_s),
            "velocity": self.injector.velocity(observation["velocity"], self._time_s),
        }
        info["faults"] = self.injector.active(self._time_s)
        return observation, info


def with_faults(env: gym.Env, faults: Iterable[str | Fault] | str | None) -> gym.Env:
    """``env`` wrapped in :class:`SensorFaults` where ``faults`` names any."""
    parsed = parse_faults(faults)
    return SensorFaults(env, parsed) if parsed else env
