"""The MPC expert laps every track on both tasks, inside the lane, faster on the racing line."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import pytest
from track_shapes import paperclip

import saferace  # noqa: F401
from saferace.agents.mpc import MPCExpert
from saferace.eval.runner import run_episode
from saferace.track import Track, builtin_track_names
from saferace.track.track_io import write_track_csv


def expert_lap(task: str, track: str) -> dict:
    env = gym.make(f"saferace/{task}-v0", track=track)
    try:
        result = run_episode(env, MPCExpert.for_env(env), seed=0)
    finally:
        env.close()
    return result.summary


def assert_clean_laps_racing_faster(track: str) -> None:
    center, racing = expert_lap("CenterLine", track), expert_lap("RacingLine", track)
    for summary in (center, racing):
        assert summary["laps_completed"] == 1
        assert summary["time_outside_lane_s"] == 0.0
        assert summary["mean_abs_deviation_m"] < 0.05
    assert racing["best_lap_time_s"] < center["best_lap_time_s"]


@pytest.mark.parametrize("track", builtin_track_names())
def test_expert_on_builtin_tracks(track: str):
    assert_clean_laps_racing_faster(track)


def test_expert_on_unseen_tracks(unseen_track_csv: Path):
    assert_clean_laps_racing_faster(str(unseen_track_csv))


def test_expert_where_two_legs_of_the_track_meet(tmp_path: Path):
    """Straights 2 m apart in a 2.4 m lane: the loader clips both legs (Montreal's hairpin)."""
    path = tmp_path / "paperclip.csv"
    write_track_csv(path, *paperclip(legs_apart_m=2.0, straight_m=12.0), 1.2, 1.2)
    assert Track.load(path).narrowing.points
    assert_clean_laps_racing_faster(str(path))
