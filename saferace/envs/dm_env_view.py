"""Every SafeRace task as a ``dm_env.Environment``, the interface of DeepMind's RL stack
(Acme and other dm_env agents), loaded the way dm_control's ``suite.load`` loads its tasks.

    from saferace.envs import dm_env_view

    env = dm_env_view.load("RacingLine", task_kwargs={"track": "lab"})
    timestep = env.reset()
    while not timestep.last():
        timestep = env.step(policy(timestep.observation))

``dm_env`` comes with dm-control, which pins the MuJoCo the scenes are built for. The
gymnasium task underneath is the same one ``gymnasium.make`` gives (same physics, cameras,
rewards and limits): a step that ends the episode is ``LAST`` with discount 0 where the task
terminated (off the track, an at-fault collision) and discount 1 where it was cut off at its
time limit; the step after ``LAST`` starts a new episode, as dm_env asks. ``info`` is what
the last step's gymnasium ``info`` said (the Frenet state, laps, cost), which dm_env has no
place for.
"""

from __future__ import annotations

from typing import Any

import dm_env
import gymnasium as gym
import numpy as np
from dm_env import specs

from saferace.errors import SafeRaceError
from saferace.names import TASK_IDS, TRAFFIC_TASK_IDS

#: Task name -> gymnasium id, for :func:`load`.
TASKS = {**TASK_IDS, **TRAFFIC_TASK_IDS}


def load(
    task_name: str, task_kwargs: dict[str, Any] | None = None, seed: int | None = None
) -> DmEnvView:
    """The task ``task_name`` (``CenterLine``, ``RacingLine`` or ``Overtake``) made with
    ``task_kwargs`` (``track``, ``image_size``, ``opponents``, ... as for ``gymnasium.make``),
    as a dm_env environment whose first episode starts from ``seed``."""
    if task_name not in TASKS:
        raise SafeRaceError(f"unknown task {task_name!r}: one of {', '.join(TASKS)}")
    return DmEnvView(gym.make(TASKS[task_name], **(task_kwargs or {})), seed=seed)


def _bounded(space: gym.spaces.Space, name: str) -> specs.BoundedArray:
    if not isinstance(space, gym.spaces.Box):
        raise SafeRaceError(f"{name}: a {type(space).__name__} space has no dm_env spec here")
    return specs.BoundedArray(space.shape, space.dtype, space.low, space.high, name=name)


class DmEnvView(dm_env.Environment):
    """A SafeRace gymnasium task seen through dm_env's interface (see the module)."""

    def __init__(self, env: gym.Env, seed: int | None = None) -> None:
        self.env = env
        self.info: dict[str, Any] = {}
        self._seed = seed
        self._needs_reset = True
        space = env.observation_space
        assert isinstance(space, gym.spaces.Dict)  # every task's observation is a dict
        self._observation_spec = {name: _bounded(part, name) for name, part in space.items()}
        self._action_spec = _bounded(env.action_space, "action")

    def reset(self) -> dm_env.TimeStep:
        observation, self.info = self.env.reset(seed=self._seed)
        self._seed = None  # later episodes go on from the task's generator
        self._needs_reset = False
        return dm_env.restart(observation)

    def step(self, action: np.ndarray) -> dm_env.TimeStep:
        if self._needs_reset:
            return self.reset()
        observation, reward, terminated, truncated, self.info = self.env.step(action)
        if terminated or truncated:
            self._needs_reset = True
            end = dm_env.termination if terminated else dm_env.truncation
            return end(float(reward), observation)
        return dm_env.transition(float(reward), observation)

    def observation_spec(self) -> dict[str, specs.BoundedArray]:
        return self._observation_spec

    def action_spec(self) -> specs.BoundedArray:
        return self._action_spec

    def close(self) -> None:
        self.env.close()
