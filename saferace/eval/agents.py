"""Agents by name for the command line: built-in drivers or ``MODULE:FACTORY``."""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from saferace.errors import SafeRaceError

RECKLESS_AGENT_NAMES = ("drift", "weave", "speeding")
BUILTIN_AGENTS = ("expert", "pure-pursuit", *RECKLESS_AGENT_NAMES)
#: Agents of the packages above ``eval``, as ``KIND:ARGUMENT``: loaded on first use (like
#: gymnasium's entry points), ``FACTORY(env, ARGUMENT, mc_samples=N, seed=S)``.
AGENT_KINDS = {"learned": "saferace.learning.agent:learned_agent"}


class Agent(Protocol):
    """Anything with ``act(observation, info) -> action``."""

    def act(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray: ...


def make_agent(
    spec: str, env, model: str = "dynamic", mc_samples: int = 10, seed: int | None = None
) -> Agent | Callable:
    """``expert`` (MPC on ``model``), ``pure-pursuit``, a reckless test agent (``drift``,
    ``weave``, ``speeding``), ``learned:CHECKPOINT`` (the control network, ``mc_samples``
    MC-dropout samples per step, masks drawn from the episode ``seed``), or
    ``MODULE:FACTORY`` with ``FACTORY(env) -> agent``."""
    if spec == "expert":  # in traffic, the expert that passes or follows the opponents
        if getattr(env.unwrapped, "traffic", None) is not None:
            from saferace.agents.traffic_expert import TrafficExpert

            return TrafficExpert.for_env(env, model=model)
        from saferace.agents.mpc import MPCExpert

        return MPCExpert.for_env(env, model=model)
    if spec == "pure-pursuit":
        from saferace.agents.pure_pursuit import PurePursuit

        return PurePursuit.for_env(env)
    if spec in RECKLESS_AGENT_NAMES:
        from saferace.agents.reckless import RECKLESS_AGENTS

        return RECKLESS_AGENTS[spec].for_env(env)
    if ":" not in spec:
        raise unknown_agent(spec)
    kind, argument = spec.split(":", 1)
    if kind in AGENT_KINDS:
        factory = load_entry_point(AGENT_KINDS[kind])
        return factory(env, argument, mc_samples=mc_samples, seed=seed)
    return load_entry_point(spec)(env)


def unknown_agent(spec: str) -> SafeRaceError:
    """The error of an agent name that is neither built in nor ``KIND:ARGUMENT``."""
    names = ", ".join(BUILTIN_AGENTS)
    return SafeRaceError(
        f"unknown agent {spec!r}: use {names}, learned:CHECKPOINT or MODULE:FACTORY"
    )


def check_agent_spec(spec: str) -> None:
    """Refuse an agent ``spec`` that cannot be made, before any setup: an unknown name, a
    learned agent's missing checkpoint, a ``MODULE:FACTORY`` that does not import (it was
    found only after seconds of building the task)."""
    if spec in BUILTIN_AGENTS:
        return
    if ":" not in spec:
        raise unknown_agent(spec)
    kind, argument = spec.split(":", 1)
    if kind in AGENT_KINDS:
        if not Path(argument).is_file():
            raise SafeRaceError(f"agent {spec!r}: no checkpoint at {argument}")
        return
    load_entry_point(spec)


def agent_files(spec: str) -> list[Path]:
    """The files an agent ``spec`` loads besides SafeRace itself: a learned agent's
    checkpoint, or the module of ``MODULE:FACTORY``; none for a built-in driver."""
    if spec in BUILTIN_AGENTS or ":" not in spec:
        return []
    kind, argument = spec.split(":", 1)
    if kind in AGENT_KINDS:
        return [Path(argument)]
    module_name = kind
    search_current_folder()
    try:
        found = importlib.util.find_spec(module_name)
    except (ImportError, ValueError):
        found = None
    if found is None or found.origin is None:
        raise SafeRaceError(f"cannot find the module of agent {spec!r}")
    return [Path(found.origin)]


def search_current_folder() -> None:
    """Find modules in the current folder too, as ``python -m`` does (the ``saferace``
    console script alone would not): where users write their agents."""
    here = os.getcwd()
    if here not in sys.path and "" not in sys.path:
        sys.path.append(here)


def load_entry_point(path: str) -> Callable:
    """The object named by ``MODULE:NAME``, its module found in the current folder too."""
    module_name, _, name = path.partition(":")
    search_current_folder()
    try:
        return getattr(importlib.import_module(module_name), name)
    except (ImportError, AttributeError) as exc:
        raise SafeRaceError(f"cannot load {path!r}: {exc}") from None


def act(
    agent: Agent | Callable, observation: dict[str, np.ndarray], info: dict[str, Any]
) -> np.ndarray:
    """Call an agent object or a plain callable."""
    method = getattr(agent, "act", None)
    if method is not None:
        return method(observation, info)
    if not callable(agent):
        raise TypeError(f"agent {agent!r} has no act() and is not callable")
    return agent(observation, info)
