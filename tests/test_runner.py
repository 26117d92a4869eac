"""Lap metrics on a hand-made trajectory, and the eval/leaderboard commands."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli

from saferace.envs.racing_env import DEFAULT_CONTROL_HZ
from saferace.eval import runner
from saferace.eval.filters import FilterConfig
from saferace.eval.leaderboard import COLUMNS, leaderboard_rows
from saferace.eval.metrics import lap_metrics, safety_step_record, summarize, thinned_trajectory
from saferace.eval.track_plots import plot_path, plt

DT = 1.0 / DEFAULT_CONTROL_HZ  # the tasks' control step


def hand_made_steps() -> dict[str, np.ndarray]:
    """10 steps; the first lap ends during step 6 (index 5); the second lap does not finish."""
    return {
        "lap": np.array([0, 0, 0, 0, 0, 1, 1, 1, 1, 1]),
        "deviation_m": np.array([0.1, -0.2, 0.0, 0.3, -0.1, 0.2, 0.0, -0.4, 0.1, 0.1]),
        "cost": np.array([0, 0, 0, 1, 0, 1, 1, 0, 0, 0], dtype=float),
        "steer_rad": np.array([0.0, 0.1, 0.1, 0.0, 0.0, 0.0, 0.05, 0.05, 0.05, 0.05]),
        "v_x_mps": np.array([0.0, 0.05, 1.0, 0.05, 0.0, 0.09, 0.05, 2.0, 2.0, 0.0]),
        "accel_mps2": np.full(10, 0.5),
    }


def test_lap_metrics_by_hand():
    laps = lap_metrics(hand_made_steps(), lap_times_s=[0.27], control_dt_s=DT)
    assert len(laps) == 2
    first, second = laps
    # Lap 0 runs during steps 0-5 (the step that completes it belongs to it).
    assert first.completed and first.lap_time_s == 0.27
    assert first.mean_abs_deviation_m == pytest.approx(np.mean([0.1, 0.2, 0.0, 0.3, 0.1, 0.2]))
    assert first.max_abs_deviation_m == pytest.approx(0.3)
    assert first.time_outside_lane_s == pytest.approx(2 * DT)
    rates = np.array([0.0, 0.1, 0.0, -0.1, 0.0, 0.0]) / DT
    assert first.steering_rate_rms_radps == pytest.approx(np.sqrt(np.mean(rates**2)))
    assert not second.completed and second.lap_time_s is None
    assert second.max_abs_deviation_m == pytest.approx(0.4)
    assert second.time_outside_lane_s == pytest.approx(DT)
    # Stopped (below 0.1 m/s) in steps 0-1, 3-6 and 9: the lap boundary splits the second stop.
    assert first.longest_stop_s == pytest.approx(3 * DT)
    assert second.longest_stop_s == pytest.approx(DT)
    summary = summarize(laps)
    assert summary["longest_stop_s"] == pytest.approx(3 * DT)
    assert summary["laps_completed"] == 1 and summary["best_lap_time_s"] == 0.27
    assert summary["time_outside_lane_s"] == pytest.approx(3 * DT)


#: 14 steps over two laps (lap 0: steps 0-8, lap 1: steps 9-13) with three stops: steps
#: 1-2 and 10-12, where the driver asks to move, and the longer 4-7.
STANDSTILL_SPEEDS_MPS = [1.0, 0.0, 0.05, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.09, 1.0]
STANDSTILL_LAPS = [0] * 8 + [1] * 6


def standstill_steps(accel_mps2: list[float]) -> dict[str, np.ndarray]:
    count = len(STANDSTILL_SPEEDS_MPS)
    return {
        "lap": np.array(STANDSTILL_LAPS),
        "deviation_m": np.zeros(count),
        "cost": np.zeros(count),
        "steer_rad": np.zeros(count),
        "v_x_mps": np.array(STANDSTILL_SPEEDS_MPS),
        "accel_mps2": np.array(accel_mps2),
    }


def test_a_standstill_counts_only_while_the_driver_asks_to_move():
    # Without a filter the driver's command is the applied one: it asks to move in the
    # stop of steps 1-2 (2 steps) and 10-12 (3 steps, lap 1); in the longer stop of steps
    # 4-7 it asks 0 and then brakes: a stop, but no standstill (counting a zero command
    # would make steps 4-6 one of 3 steps).
    plain = standstill_steps(
        [0.5, 0.5, 0.5, 0.5, 0.0, 0.0, 0.0, -1.0, 1.0, 1.0, 0.2, 0.2, 0.2, 0.0]
    )
    first, second = lap_metrics(plain, [0.45], DT)
    assert first.longest_stop_s == pytest.approx(4 * DT)
    assert first.longest_standstill_s == pytest.approx(2 * DT)
    assert second.longest_standstill_s == pytest.approx(3 * DT)
    assert summarize([first, second])["longest_standstill_s"] == pytest.approx(3 * DT)
    # Behind a filter the driver's command is the nominal one, recorded per step: in steps
    # 4-7 it asks 0.8 m/s^2 while the filter brakes (applied < 0), which counts; in steps
    # 1-2 the filter pushes (applied 0.5) while the driver asks nothing, which does not.
    nominal = [0.5, 0.0, 0.0, 0.5, 0.8, 0.8, 0.8, 0.8, 1.0, 1.0, 0.2, 0.2, 0.2, 0.0]
    applied = [0.5, 0.5, 0.5, 0.5, -1.0, -0.5, -2.0, -0.2, 1.0, 1.0, 0.2, 0.2, 0.2, 0.0]
    records = [
        safety_step_record(
            {
                "nominal_action": [0.0, asked],
                "filtered_action": [0.0, given],
                "intervened": asked != given,
                "slacks": {"lane": 0.0},
                "fallback": "",
                "alarm": False,
                "covered": True,
                "solve_time_s": 1e-4,
                "filter_time_s": 2e-4,
                "clipped": False,
            }
        )
        for asked, given in zip(nominal, applied, strict=True)
    ]
    filtered = {
        **standstill_steps(applied),
        **{name: np.array([record[name] for record in records]) for name in records[0]},
    }
    assert filtered["nominal_accel_mps2"].tolist() == nominal
    first, second = lap_metrics(filtered, [0.45], DT)
    assert first.longest_stop_s == pytest.approx(4 * DT)
    assert first.longest_standstill_s == pytest.approx(4 * DT)
    assert second.longest_standstill_s == pytest.approx(3 * DT)
    assert summarize([first, second])["longest_standstill_s"] == pytest.approx(4 * DT)


def test_a_filtered_episode_records_the_drivers_own_acceleration():
    env = runner.make_task_env("CenterLine", "lab", 1, FilterConfig(kind="cbf"), 0, max_steps=5)
    try:
        result = runner.run_episode(env, lambda observation, info: np.array([0.0, 1.5]), seed=0)
    finally:
        env.close()
    assert result.steps["nominal_accel_mps2"].tolist() == [1.5] * 5
    assert result.summary["longest_standstill_s"] == 0.0  # it drove off at once


def test_the_progress_line_and_the_leaderboard_show_the_longest_standstill():
    summary = {"laps_completed": 0, "mean_lap_time_s": None, "time_outside_lane_s": 0.0}
    held = {**summary, "longest_standstill_s": 12.5}
    assert runner.episode_words(held) == "0 laps, 0.00 s outside, longest standstill 12.50 s"
    assert runner.episode_words(summary).endswith("longest standstill -")  # an old row
    rows = [
        {"agent": "a", "task": "CenterLine", "track": "lab", "summary": {**summary, **values}}
        for values in (
            {"longest_standstill_s": 12.5, "best_lap_time_s": None, "max_abs_deviation_m": 0.1},
            {"longest_standstill_s": 0.5, "best_lap_time_s": None, "max_abs_deviation_m": 0.1},
        )
    ]
    (line,) = leaderboard_rows(rows)
    assert line[COLUMNS.index("longest standstill [s]")] == 12.5  # the longest seed's
    assert line[COLUMNS.index("laps completed")] == 0
    old_summary = {k: v for k, v in rows[1]["summary"].items() if k != "longest_standstill_s"}
    (line,) = leaderboard_rows([rows[0], {**rows[1], "summary": old_summary}])
    assert line[COLUMNS.index("longest standstill [s]")] is None  # not a longest of some


def test_a_thinned_path_keeps_a_one_step_exit_and_the_plot_marks_it():
    x_m = np.arange(1000, dtype=float)
    cost = np.zeros(1000)
    cost[503] = 1.0  # one step outside, between two kept points
    trajectory = thinned_trajectory({"x_m": x_m, "y_m": -x_m, "cost": cost}, ("x_m", "y_m"))
    assert len(trajectory["x_m"]) == len(trajectory["outside"]) == 500
    assert trajectory["x_m"][:2] == [0.0, 2.0]
    assert np.flatnonzero(trajectory["outside"]).tolist() == [251]  # steps 502-503
    figure, ax = plt.subplots()
    plot_path(ax, trajectory, color="tab:blue")
    plot_path(ax, {"x_m": [0.0, 1.0], "y_m": [0.0, 1.0]})  # a result without ``outside``
    path, cross, _without_crosses = ax.lines
    assert cross.get_marker() == "x" and cross.get_color() == path.get_color()
    assert cross.get_xdata().tolist() == [502.0]
    plt.close(figure)


@pytest.mark.parametrize(("status", "expected"), [("", "abc123"), (" M x.py\n", "abc123+dirty")])
def test_the_git_revision_is_read_once_per_process_and_marks_a_dirty_tree(
    monkeypatch, status: str, expected: str
):
    """A commit made while a long table runs must not relabel the rows of code loaded
    before it; rows of uncommitted code say so."""
    calls = []

    def fake_git(args: list[str], **_) -> subprocess.CompletedProcess:
        calls.append(args[1])
        out = {"rev-parse": "abc123\n", "status": status}[args[1]]
        return subprocess.CompletedProcess(args, 0, out, "")

    runner.git_revision.cache_clear()
    monkeypatch.setattr(runner.subprocess, "run", fake_git)
    try:
        assert runner.git_revision() == runner.git_revision() == expected
        assert calls == ["rev-parse", "status"]
    finally:
        runner.git_revision.cache_clear()


def test_no_steps_no_laps():
    empty = {name: np.array([]) for name in hand_made_steps()}
    assert lap_metrics(empty, [], DT) == []


def test_eval_rows_and_leaderboard(tmp_path: Path):
    results = tmp_path / "results.jsonl"
    first = run_cli(
        "eval",
        "--agent",
        "pure-pursuit",
        "--task",
        "CenterLine",
        "--track",
        "lab",
        "--seeds",
        "0",
        "1",
        "--out",
        str(results),
    )
    assert first.returncode == 0, first.stderr
    second = run_cli(
        "eval",
        "--agent",
        "expert",
        "--model",
        "kinematic",
        "--task",
        "RacingLine",
        "--track",
        "lab",
        "--out",
        str(results),
    )
    assert second.returncode == 0, second.stderr
    rows = [json.loads(line) for line in results.read_text().splitlines()]
    assert [(r["agent"], r["task"], r["seed"]) for r in rows] == [
        ("pure-pursuit", "CenterLine", 0),
        ("pure-pursuit", "CenterLine", 1),
        ("expert", "RacingLine", 0),
    ]
    for row in rows:
        assert row["summary"]["laps_completed"] == 1
        assert row["summary"]["time_outside_lane_s"] == 0.0
        assert row["summary"]["longest_standstill_s"] == 0.0  # starts rolling, never stops
        assert {
            "saferace_version",
            "git_revision",
            "packages",
            "config",
            "trajectory",
        } <= row.keys()
        assert row["packages"]["mujoco"] == "3.17.0"
        assert row["filter"]["kind"] == "none"  # every row names its filter
        assert row["config"]["track"] == "lab" and row["config"]["track_sha256"] is None
    assert rows[2]["solver"]["solve_median_ms"] > 0.0
    plot, table = tmp_path / "board.png", tmp_path / "board.csv"
    board = run_cli("leaderboard", str(results), "--plot", str(plot), "--csv", str(table))
    assert board.returncode == 0, board.stderr
    lines = [line for line in board.stdout.splitlines() if line.startswith("|")]
    header, _, *body = [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]
    columns = [header.index(name) for name in ("agent", "task", "track")]
    assert sorted(tuple(cells[i] for i in columns) for cells in body) == [
        ("expert", "RacingLine", "lab"),
        ("pure-pursuit", "CenterLine", "lab"),
    ]  # one line per (agent, task, track)
    assert all(cells[header.index("longest standstill [s]")] == "0.000" for cells in body)
    assert plot.stat().st_size > 20_000 and table.read_text().count("\n") == 3


def test_leaderboard_without_results_is_a_clear_error(tmp_path: Path):
    result = run_cli("leaderboard", str(tmp_path / "missing.jsonl"))
    assert result.returncode == 2
    assert "results: no such file or folder" in result.stderr and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_a_run_says_how_it_ended():
    """Its laps done, the car out of its lane (terminated), or the time limit; behind a
    filter, a car standing at the time limit is named as stopped by the filter."""
    last = {"lap": 0, "time_s": 0.65, "v_x_mps": 0.0, "fully_outside_lane": True}
    assert runner.episode_ending(last, True, 1, False) == "ended: the car left its lane at 0.65 s"
    flipped = {**last, "fully_outside_lane": False}
    assert runner.episode_ending(flipped, True, 1, False) == "ended: the car flipped at 0.65 s"
    done = {"lap": 2, "time_s": 20.0, "v_x_mps": 3.0}
    assert runner.episode_ending(done, False, 2, True) == "ended: 2 of 2 laps done"
    standing = {"lap": 0, "time_s": 40.0, "v_x_mps": 0.02}
    assert runner.episode_ending(standing, False, 1, True) == (
        "ended: the time limit, 0 of 1 laps done, the car standing (stopped by the filter)"
    )
    assert runner.episode_ending(standing, False, 1, False) == (
        "ended: the time limit, 0 of 1 laps done"
    )
    summary = {"laps_completed": 0, "mean_lap_time_s": None, "time_outside_lane_s": 0.15}
    assert runner.episode_words(summary, "ended: x").endswith("longest standstill -; ended: x")


@pytest.mark.parametrize("command", ["drive", "eval"])
def test_a_run_that_leaves_its_lane_says_so(command: str, tmp_path: Path):
    """The unfiltered weave agent leaves lab's lane within a second: ``eval`` says so on
    its episode's line, ``drive`` too; both exit 0 (the run finished; it drove badly)."""
    out = ["--out", str(tmp_path / "rows.jsonl")] if command == "eval" else []
    result = run_cli(command, "--agent", "weave", "--track", "lab", *out)
    assert "ended: the car left its lane at 0.6" in result.stderr + result.stdout
    assert result.returncode == 0
