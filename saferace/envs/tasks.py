"""The registered tasks' entry points: each task's env, wrapped in the sensor faults its
``faults`` argument names (:mod:`saferace.faults`)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import gymnasium as gym

from saferace.envs.overtake import OvertakeEnv
from saferace.envs.racing_env import CenterLineEnv, RacingLineEnv
from saferace.faults import Fault, with_faults


def CenterLine(faults: Iterable[str | Fault] | str | None = None, **kwargs: Any) -> gym.Env:  # noqa: N802  (the task's name)
    """``saferace/CenterLine-v0``: :class:`~saferace.envs.racing_env.CenterLineEnv`."""
    return with_faults(CenterLineEnv(**kwargs), faults)


def RacingLine(faults: Iterable[str | Fault] | str | None = None, **kwargs: Any) -> gym.Env:  # noqa: N802
    """``saferace/RacingLine-v0``: :class:`~saferace.envs.racing_env.RacingLineEnv`."""
    return with_faults(RacingLineEnv(**kwargs), faults)


def Overtake(faults: Iterable[str | Fault] | str | None = None, **kwargs: Any) -> gym.Env:  # noqa: N802
    """``saferace/Overtake-v0``: :class:`~saferace.envs.overtake.OvertakeEnv`."""
    return with_faults(OvertakeEnv(**kwargs), faults)
