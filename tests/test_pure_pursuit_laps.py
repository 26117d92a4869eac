"""The pure-pursuit driver laps every built-in track on both tasks without leaving the lane."""

from __future__ import annotations

import gymnasium as gym
import pytest

import saferace  # noqa: F401
from saferace.agents.pure_pursuit import PurePursuit
from saferace.registry import TASKS
from saferace.track import builtin_track_names


@pytest.mark.parametrize("task_id", sorted(TASKS))
@pytest.mark.parametrize("track", builtin_track_names())
def test_pure_pursuit_completes_a_clean_lap(task_id: str, track: str):
    env = gym.make(task_id, track=track)
    agent = PurePursuit.for_env(env)
    observation, info = env.reset(seed=0)
    dt = env.unwrapped.control_dt_s
    steps, outside = 0, 0.0
    terminated = truncated = False
    while not (terminated or truncated):
        observation, _, terminated, truncated, info = env.step(agent.act(observation, info))
        steps += 1
        outside += info["cost"]
    assert not terminated
    assert info["lap"] == 1 and info["lap_completed"]
    assert outside == 0.0
    # The lap ends inside the last step: its time is within one step of the simulated time.
    assert info["time_s"] - dt <= info["lap_time_s"] <= info["time_s"] + 1e-9
    assert info["time_s"] == pytest.approx(steps * dt)
    env.close()
