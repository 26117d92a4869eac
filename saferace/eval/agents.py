"""Agents by name for the command line: built-in drivers or ``MODULE:FACTORY``."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from saferace.errors import SafeRaceError


class Agent(Protocol):
    """Anything with ``act(observation, info) -> action``."""

    def act(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray: ...


def make_agent(spec: str, env, model: str = "dynamic") -> Agent | Callable:
    """``expert`` (MPC), ``pure-pursuit``, or ``MODULE:FACTORY`` with ``FACTORY(env) -> agent``."""
    if spec == "expert":
        from saferace.agents.mpc import MPCExpert

        return MPCExpert.for_env(env, model=model)
    if spec == "pure-pursuit":
        from saferace.agents.pure_pursuit import PurePursuit

        return PurePursuit.for_env(env)
    if ":" not in spec:
        raise SafeRaceError(f"unknown agent {spec!r}: use expert, pure-pursuit or MODULE:FACTORY")
    module_name, factory_name = spec.split(":", 1)
    try:
        factory = getattr(importlib.import_module(module_name), factory_name)
    except (ImportError, AttributeError) as exc:
        raise SafeRaceError(f"cannot load agent factory {spec!r}: {exc}") from None
    return factory(env)


def act(
    agent: Agent | Callable, observation: dict[str, np.ndarray], info: dict[str, Any]
) -> np.ndarray:
    """Call an agent object or a plain callable."""
    method = getattr(agent, "act", None)
    return method(observation, info) if method is not None else agent(observation, info)
