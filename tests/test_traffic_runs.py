"""Traffic through the suite's commands: the runner's collision and overtake counts, rows
and plots that show the opponents, collection labelled by the expert in traffic, and
DAgger runs among opponents."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from cli_helpers import run_cli

import saferace  # noqa: F401  - registers the tasks
from saferace.eval.leaderboard import AT_FAULT_LABEL, NOT_AT_FAULT_LABEL, plot_traffic
from saferace.eval.metrics import traffic_summary
from saferace.eval.runner import read_jsonl
from saferace.eval.track_plots import plt
from saferace.learning.collect import collect_round
from saferace.learning.configs import CollectionConfig, DaggerConfig, EpisodeSettings

#: On lab's 0.8 m lane a car cannot pass another: the expert must follow this one.
SLOW_CAR = "pure-pursuit:gap_m=2.5,speed_factor=0.5,lateral_offset_m=0"


def test_the_episode_counts_collisions_and_the_opponents_it_passed():
    steps = {
        "time_s": np.arange(4) * 0.05,
        "collisions": np.array([0, 1, 0, 1]),
        "at_fault_collisions": np.array([0, 1, 0, 0]),
        # leads on four cars: passed; still ahead; lapped; started behind, stayed behind
        "opponents_lead_m": np.array(
            [
                [-2.0, -2.0, -3.0, 1.5],
                [-1.0, -2.5, 5.0, 1.0],
                [0.1, -3.0, 20.0, 1.2],
                [0.3, -3.5, 40.0, 1.4],
            ]
        ),
    }
    assert traffic_summary(steps) == {"collisions": 2, "at_fault_collisions": 1, "overtakes": 2}


def test_the_ego_lead_counts_from_each_opponents_start():
    env = gym.make("saferace/Overtake-v0", track="oval")
    _, info = env.reset(seed=0)
    [opponent] = info["opponents"]
    assert opponent["ego_lead_m"] == pytest.approx(-2.0, abs=1e-6)
    for _ in range(20):  # the ego brakes, the opponent drives on
        _, _, _, _, info = env.step(np.array([0.0, -4.0]))
    [opponent] = info["opponents"]
    assert opponent["ego_lead_m"] == pytest.approx(
        info["progress_m"] - opponent["progress_m"] - 2.0
    )
    assert opponent["ego_lead_m"] < -2.2  # the opponent drew away
    env.close()


def test_collection_in_traffic_is_labelled_by_the_expert_that_follows(tmp_path: Path):
    settings = EpisodeSettings(laps=1, max_seconds=8.0)
    alone = collect_round(
        tmp_path / "alone", CollectionConfig(track="lab", episode=settings), progress=False
    )
    among = collect_round(
        tmp_path / "among",
        CollectionConfig(track="lab", opponents=(SLOW_CAR,), episode=settings),
        progress=False,
    )
    [episode] = among.episodes
    assert episode["at_fault_collisions"] == 0 and episode["collisions"] == 0
    assert episode["overtakes"] == 0 and episode["time_outside_lane_s"] == 0.0
    manifest = json.loads((among.path / "manifest.json").read_text())
    assert manifest["config"]["opponents"] == [SLOW_CAR]

    def label_speeds(collected) -> np.ndarray:
        frames = np.load(collected.path / "frames.npz")
        return frames["expert"][:, 1]

    # the labels ask for the slow car's pace where the expert alone would race on
    assert np.mean(label_speeds(among)[-60:]) < 0.75 * np.mean(label_speeds(alone)[-60:])


def test_a_dagger_run_among_opponents_is_another_run():
    plain = DaggerConfig(track="lab")
    among = DaggerConfig(track="lab", task="Overtake", opponents=(SLOW_CAR,))
    assert "opponents" not in plain.fingerprint  # runs made before the option are the same
    assert among.fingerprint["opponents"] == [SLOW_CAR]
    assert among.fingerprint["task"] == "Overtake"


def test_eval_among_opponents_records_them_and_the_leaderboard_shows_them(tmp_path: Path):
    rows_path = tmp_path / "rows.jsonl"
    result = run_cli(
        "eval", "--agent", "speeding", "--task", "RacingLine", "--track", "lab",
        "--opponents", SLOW_CAR, "--max-seconds", "6", "--out", str(rows_path),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    [row] = read_jsonl(rows_path)
    assert row["config"]["env"]["opponents"] == [SLOW_CAR]
    assert row["summary"]["at_fault_collisions"] >= 1  # unfiltered, it runs into the slow car
    [path] = row["traffic"]["opponents"]
    assert len(path["x_m"]) == len(row["trajectory"]["x_m"])
    assert any(hit["at_fault"] for hit in row["traffic"]["collisions"])
    board = run_cli("leaderboard", str(rows_path), "--plot", str(tmp_path / "paths.png"))
    assert board.returncode == 0, board.stderr
    assert SLOW_CAR in board.stdout
    assert (tmp_path / "paths.png").stat().st_size > 20_000


def test_the_plot_draws_each_opponent_and_marks_collisions_by_fault():
    traffic = {
        "opponents": [{"x_m": [0.0, 1.0], "y_m": [0.0, 0.0]}, {"x_m": [2.0], "y_m": [1.0]}],
        "collisions": [
            {"time_s": 1.0, "x_m": 1.0, "y_m": 0.0, "at_fault": True},
            {"time_s": 2.0, "x_m": 2.0, "y_m": 1.0, "at_fault": False},
        ],
    }
    figure, axis = plt.subplots()
    plot_traffic(axis, traffic, "C1")
    plot_traffic(axis, None, "C2")  # a row alone on the track draws nothing
    lines = axis.get_lines()
    assert [line.get_linestyle() for line in lines[:2]] == [":", ":"]
    stars = {line.get_label(): line.get_color() for line in lines if line.get_marker() == "*"}
    assert stars == {AT_FAULT_LABEL: "red", NOT_AT_FAULT_LABEL: "orange"}
    plt.close(figure)


@pytest.mark.slow  # 15-30 s: the default suite stays within 15 min on 2 cores
def test_the_filter_sees_the_opponents_with_the_noise_asked_for(tmp_path: Path):
    rows_path = tmp_path / "rows.jsonl"
    common = ("eval", "--agent", "speeding", "--track", "lab", "--opponents", SLOW_CAR)
    result = run_cli(
        *common, "--filter", "cbf", "--opponent-noise", "0.05", "--max-seconds", "4",
        "--out", str(rows_path),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    [row] = read_jsonl(rows_path)
    assert row["filter"]["opponent_noise_m"] == 0.05
    assert row["summary"]["at_fault_collisions"] == 0
    assert "opponents seen with 0.05 m noise" in result.stdout
    for refused, reason in (
        (("--opponent-noise", "0.05"), "need --filter cbf"),
        (("--filter", "cbf", "--opponent-noise", "-1"), "--opponent-noise: must be at least 0"),
        (("--filter", "mpsf", "--opponent-noise", "0.05"), "the predictive filter (mpsf) has none"),
    ):
        result = run_cli(*common, *refused, "--out", str(tmp_path / "no.jsonl"))
        assert result.returncode != 0 and reason in result.stderr, result.stderr
