"""``gymnasium.make_vec`` runs the tasks in subprocesses (EGL in each) like single envs."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  - registers the tasks


@pytest.mark.parametrize("context", ["spawn", "forkserver"])
def test_async_vector_env_steps_like_single_envs(context: str):
    vector = gym.make_vec(
        "saferace/RacingLine-v0", num_envs=2, vectorization_mode="async",
        vector_kwargs={"context": context}, track="lab", randomize="mild",
    )  # fmt: skip
    singles = [gym.make("saferace/RacingLine-v0", track="lab", randomize="mild") for _ in range(2)]
    observations, _ = vector.reset(seed=[3, 4])
    for k, env in enumerate(singles):
        single, _ = env.reset(seed=3 + k)
        np.testing.assert_array_equal(observations["image"][k], single["image"])
    assert not np.array_equal(observations["image"][0], observations["image"][1])  # two looks
    actions = np.array([[0.02, 1.0], [-0.02, 0.5]], np.float32)  # stays inside
    for _ in range(10):
        observations, rewards, _, _, infos = vector.step(actions)
        steps = [env.step(action) for env, action in zip(singles, actions, strict=True)]
    for k, (single, reward, terminated, _, info) in enumerate(steps):
        assert not terminated  # no episode ended, so the vector env reset none
        np.testing.assert_array_equal(observations["image"][k], single["image"])
        assert rewards[k] == reward and infos["s_m"][k] == info["s_m"]
    vector.close()
    for env in singles:
        env.close()


FORK_AFTER_RENDERING = """
import gymnasium as gym, saferace
gym.make("saferace/CenterLine-v0", track="lab").reset(seed=0)  # this process renders
vector = gym.make_vec("saferace/CenterLine-v0", num_envs=2, vectorization_mode="async")
vector.reset(seed=0)  # forked children: they must refuse, not hang
"""


def test_forked_children_of_a_rendering_process_refuse_instead_of_hanging():
    result = subprocess.run(
        [sys.executable, "-c", FORK_AFTER_RENDERING], capture_output=True, text=True, timeout=120
    )
    assert result.returncode != 0
    assert "offscreen OpenGL does not survive a fork" in result.stderr
    assert 'vector_kwargs={"context": "spawn"}' in result.stderr
