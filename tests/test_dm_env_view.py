"""Every task through dm_env's interface, checked with dm_env's own environment test mixin
(specs, FIRST/MID/LAST, a new episode after LAST), and the view agrees with the gymnasium
task underneath step for step."""

from __future__ import annotations

import unittest

import dm_env
import gymnasium as gym
import numpy as np
import pytest
from dm_env import test_utils

import saferace  # noqa: F401  (registers the tasks)
from saferace.envs import dm_env_view
from saferace.errors import SafeRaceError

SMALL = {"track": "lab", "image_size": (32, 32), "max_steps": 12}


class _TaskTest(test_utils.EnvironmentTestMixin):
    task = ""

    def make_object_under_test(self) -> dm_env.Environment:
        return dm_env_view.load(self.task, SMALL, seed=0)

    def make_action_sequence(self):
        """Past the 12-step limit: the episode ends (LAST), and the next step starts one."""
        for step in range(30):
            yield np.array([0.05 * np.sin(step), 1.0], dtype=np.float32)


class CenterLineTest(_TaskTest, unittest.TestCase):
    task = "CenterLine"


class RacingLineTest(_TaskTest, unittest.TestCase):
    task = "RacingLine"


class OvertakeTest(_TaskTest, unittest.TestCase):
    task = "Overtake"


def test_the_view_steps_as_the_gymnasium_task_and_ends_as_it_does():
    view = dm_env_view.load("RacingLine", SMALL, seed=3)
    env = gym.make("saferace/RacingLine-v0", **SMALL)
    observation, _ = env.reset(seed=3)
    first = view.reset()
    np.testing.assert_array_equal(first.observation["image"], observation["image"])
    action = np.array([0.0, 1.0], dtype=np.float32)
    for index in range(SMALL["max_steps"]):
        observation, reward, terminated, truncated, info = env.step(action)
        step = view.step(action)
        np.testing.assert_array_equal(step.observation["velocity"], observation["velocity"])
        assert step.reward == pytest.approx(reward) and view.info["s_m"] == info["s_m"]
        assert step.last() == (terminated or truncated), index
    assert truncated and not terminated and step.discount == 1.0  # cut off: not terminal
    assert view.step(action).first()  # after LAST, a new episode
    view.close()
    env.close()


def test_a_task_that_ends_off_the_track_ends_with_discount_zero():
    view = dm_env_view.load("CenterLine", {"track": "lab", "image_size": (32, 32)}, seed=0)
    view.reset()
    step = view.step(np.array([0.36, 4.0], dtype=np.float32))
    while not step.last():
        step = view.step(np.array([0.36, 4.0], dtype=np.float32))
    assert step.discount == 0.0 and view.info["outside_lane"]
    view.close()


def test_an_unknown_task_is_refused():
    with pytest.raises(SafeRaceError, match="unknown task 'Drift': one of CenterLine"):
        dm_env_view.load("Drift")


def test_the_seed_starts_the_first_episode_and_the_next_go_on_from_it():
    """Random starts: the same seed draws the same episodes in two views, another seed
    others, and the second episode is not the first again (the seed is used once)."""

    def starts(seed: int) -> list[float]:
        view = dm_env_view.load("CenterLine", {**SMALL, "random_start": True}, seed=seed)
        drawn = []
        for _ in range(3):
            view.reset()
            drawn.append(float(view.info["s_m"]))
        view.close()
        return drawn

    first = starts(5)
    assert starts(5) == first
    assert starts(6)[0] != first[0]
    assert len(set(first)) == 3
