"""The expert's labels computed where the env runs, for episodes driven together.

Collecting N episodes of a learned driver at once in lockstep
(:func:`~saferace.learning.collect.collect_round` with ``num_envs``), the envs run in
worker processes; the expert MPC that labels every frame is
the costliest part of a step after rendering, so it runs there too: :class:`ExpertLabels`
wraps the env and puts the expert's action and planned speed for each new observation into
``info``, and :class:`LabelsFromInfo` hands them to the
:class:`~saferace.learning.collect.LabellingDriver` in place of the expert. The labels are
the ones the expert would give in the labeller's own process: it sees the same
observations and infos, reset after the env as there.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from saferace.agents.mpc import MPCExpert
from saferace.eval.agents import make_agent

#: Where :class:`ExpertLabels` puts the expert's ``action`` and ``planned_speed_mps``.
LABEL_KEY = "expert_label"


def labelling_expert(env: gym.Env, expert_model: str) -> MPCExpert:
    """The expert that labels ``env``'s frames (in traffic, the one that plans around the
    opponents)."""
    expert = make_agent("expert", env, expert_model)
    assert isinstance(expert, MPCExpert), "the expert is an MPC"
    return expert


class ExpertLabels(gym.Wrapper):
    """The expert (``make_agent("expert", ...)``) acting on every observation ``env``
    returns; its action and planned speed in ``info[LABEL_KEY]``."""

    def __init__(self, env: gym.Env, expert_model: str) -> None:
        super().__init__(env)
        self.expert = labelling_expert(env, expert_model)

    def reset(self, **kwargs: Any) -> tuple[Any, dict]:
        observation, info = self.env.reset(**kwargs)
        self.expert.reset()
        return observation, self._labelled(observation, info)

    def step(self, action: Any) -> tuple:
        observation, reward, terminated, truncated, info = self.env.step(action)
        return observation, reward, terminated, truncated, self._labelled(observation, info)

    def _labelled(self, observation: dict, info: dict) -> dict:
        action = np.asarray(self.expert.act(observation, info))
        label = {"action": action, "planned_speed_mps": self.expert.planned_speed_mps()}
        return {**info, LABEL_KEY: label}


class LabelsFromInfo:
    """The expert as a labeller sees it, read from ``info[LABEL_KEY]``."""

    def __init__(self) -> None:
        self._planned_speed_mps = 0.0

    def reset(self) -> None:
        """Nothing to reset: the expert resets with its env."""

    def act(self, observation: dict, info: dict) -> np.ndarray:
        label = info[LABEL_KEY]
        self._planned_speed_mps = label["planned_speed_mps"]
        return label["action"]

    def planned_speed_mps(self) -> float:
        return self._planned_speed_mps
