"""Typed access to the SafeRace env under a (possibly wrapped) gymnasium env."""

from __future__ import annotations

from typing import cast

import gymnasium as gym

from saferace.envs.racing_env import RacingEnv


def racing_env(env: gym.Env) -> RacingEnv:
    """The SafeRace env under ``env``'s wrappers, typed as such: for reading its ``track``,
    ``reference``, ``control_dt_s`` and the like (not checked: the caller knows ``env`` is a
    SafeRace task)."""
    return cast(RacingEnv, env.unwrapped)
