"""``saferace robustness``: a driver per look, resumable, with the state network scored."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from saferace.errors import ConfigError, SafeRaceError
from saferace.eval.filters import FilterConfig
from saferace.experiments import robustness
from saferace.experiments.robustness import (
    TABLE_COLUMNS,
    TRACK_COLUMNS,
    RobustnessConfig,
    plot_robustness,
    robustness_rows,
    run_robustness,
    track_rows,
)
from saferace.track.track_io import write_track_csv
from tests.track_shapes import paperclip


def short(agent: str, **kwargs) -> RobustnessConfig:
    return RobustnessConfig(
        agent=agent, task="CenterLine", tracks=("lab",), presets=("none", "strong"), seeds=(0,),
        max_seconds=2.0, model="kinematic", **kwargs,
    )  # fmt: skip


def test_runs_are_kept_and_not_driven_again(tmp_path: Path, monkeypatch):
    config = short("pure-pursuit")
    runs = run_robustness(config, tmp_path, progress=False)
    assert [(run["look"], run["seed"]) for run in runs] == [("none", 0), ("strong", 0)]
    assert all(0.0 < run["completion"] < 1.0 for run in runs)  # 2 s of a 24 m lap
    assert all(run["longest_standstill_s"] == 0.0 for run in runs)  # it never stops

    def must_not_drive(*args, **kwargs):
        raise AssertionError("a finished run was driven again")

    monkeypatch.setattr(robustness, "drive_once", must_not_drive)
    assert run_robustness(config, tmp_path, progress=False) == runs
    with pytest.raises(SafeRaceError, match=r"other settings.*agent"):
        run_robustness(short("expert"), tmp_path, progress=False)


def test_the_state_network_is_scored_beside_and_behind_the_filter(tmp_path: Path, tiny_checkpoint):
    checkpoint, _ = tiny_checkpoint(False)
    monitored = short("pure-pursuit", monitor_state_source=f"learned:{checkpoint}")
    filtered = short(
        "pure-pursuit",
        safety=FilterConfig(kind="cbf", state_source=f"learned:{checkpoint}", samples=3),
    )
    for name, config in (("monitored", monitored), ("filtered", filtered)):
        runs = run_robustness(config, tmp_path / name, progress=False)
        for run in runs:
            assert run["e_y_error_m"] > 0.0 and run["e_y_spread_m"] > 0.0
            assert 0.0 <= run["truth_within_2_spreads"] <= 1.0
        rows = robustness_rows(runs, config.presets)
        assert [row[0] for row in rows] == ["none", "strong"]
        assert all(len(row) == len(TABLE_COLUMNS) for row in rows)
        plot_robustness(runs, config.presets, tmp_path / f"{name}.png")
        assert (tmp_path / f"{name}.png").stat().st_size > 10_000
    assert runs[0]["intervention_rate"] is not None  # the filtered runs


def test_the_tables_show_the_longest_standstill_beside_completion_and_time_outside():
    """A run held still while its driver asks to go (no time outside, no progress) shows
    in its look's and its track's lines; a look with a run from before the measurement
    shows none rather than the longest of the others."""

    def measured(track: str, look: str, completion: float, standstill_s: float | None) -> dict:
        run = {"track": track, "look": look, "seed": 0, "completion": completion,
               "laps_completed": int(completion == 1.0), "lap_time_s": None,
               "time_outside_lane_s": 0.0, "min_lane_barrier_m": 0.2, "scored_steps": 10,
               "covered_steps": 10, "alarm_rate": 0.0}  # fmt: skip
        return run if standstill_s is None else {**run, "longest_standstill_s": standstill_s}

    runs = [
        measured("lab", "none", 1.0, 0.0),
        measured("oval", "none", 0.1, 37.5),
        measured("lab", "strong", 1.0, 0.5),
        measured("oval", "strong", 1.0, None),
    ]
    looks = {row[0]: dict(zip(TABLE_COLUMNS, row, strict=True))
             for row in robustness_rows(runs, ("none", "strong"))}  # fmt: skip
    assert looks["none"]["longest standstill [s]"] == 37.5
    assert looks["none"]["completion [%]"] == pytest.approx(55.0)
    assert looks["none"]["time outside lane [s]"] == 0.0
    assert looks["strong"]["longest standstill [s]"] == "-"
    tracks = {(row[0], row[1]): dict(zip(TRACK_COLUMNS, row, strict=True))
              for row in track_rows(runs, ("none", "strong"))}  # fmt: skip
    assert tracks[("oval", "none")]["longest standstill [s]"] == 37.5
    assert tracks[("lab", "none")]["longest standstill [s]"] == 0.0
    assert tracks[("lab", "strong")]["longest standstill [s]"] == 0.5


def test_a_second_state_network_beside_the_filters_is_refused():
    with pytest.raises(SafeRaceError, match="scored already"):
        short(
            "expert",
            safety=FilterConfig(kind="cbf", state_source="learned:a.pt"),
            monitor_state_source="learned:b.pt",
        )


def test_a_track_edited_under_the_same_name_is_driven_again(tmp_path: Path, monkeypatch):
    """Runs are kept by the track's content as well as its name: a rerun after the CSV's
    lane changed drives every run again (before, it kept the old lane's rows)."""
    driven: list[str] = []

    def drive(config, track, preset, seed, progress):
        driven.append(preset)
        return {"completion": 1.0}

    monkeypatch.setattr(robustness, "drive_once", drive)
    track = tmp_path / "mine.csv"
    write_track_csv(track, *paperclip(legs_apart_m=6.0, straight_m=10.0), 0.5, 0.5)
    config = replace(short("pure-pursuit"), tracks=(str(track),))
    run_robustness(config, tmp_path / "out", progress=False)
    run_robustness(config, tmp_path / "out", progress=False)
    assert driven == ["none", "strong"]  # kept
    write_track_csv(track, *paperclip(legs_apart_m=6.0, straight_m=10.0), 0.5, 0.6)
    rows = run_robustness(config, tmp_path / "out", progress=False)
    assert driven == ["none", "strong"] * 2 and len(rows) == 2


def test_settings_with_tuples_resume(tmp_path: Path):
    config = short("pure-pursuit", safety=FilterConfig(kind="cbf", state_noise=(0.05, 0.05)))
    first = run_robustness(replace(config, presets=("none",)), tmp_path, progress=False)
    both = run_robustness(config, tmp_path, progress=False)  # read back from JSON: lists
    assert both[0] == first[0] and len(both) == 2


def test_tracks_and_shift_severities_score_the_filters_interval(tmp_path: Path, tiny_checkpoint):
    checkpoint, _ = tiny_checkpoint(False)
    config = replace(
        short(
            "pure-pursuit",
            safety=FilterConfig(
                kind="cbf", state_source=f"learned:{checkpoint}", samples=3, uncertainty="robust"
            ),
        ),
        tracks=("lab", "oval"),
        presets=("severity-0", "severity-5"),
        max_seconds=1.0,
    )
    runs = run_robustness(config, tmp_path, progress=False)
    assert sorted((run["track"], run["look"]) for run in runs) == [
        ("lab", "severity-0"), ("lab", "severity-5"),
        ("oval", "severity-0"), ("oval", "severity-5"),
    ]  # fmt: skip
    for run in runs:
        steps = run["scored_steps"]
        assert 1 <= steps <= 20 and 0 <= run["covered_steps"] <= steps  # at most 1 s at 20 Hz
        assert run["coverage"] == pytest.approx(run["covered_steps"] / steps)
        assert run["e_y_half_width_m"] > 0.0 and run["alarm_rate"] is not None
    rows = robustness_rows(runs, config.presets)
    coverage = rows[0][TABLE_COLUMNS.index("coverage [%] (95% band)")]
    plain = [r for r in runs if r["look"] == "severity-0"]
    share = sum(r["covered_steps"] for r in plain) / sum(r["scored_steps"] for r in plain)
    assert coverage.startswith(f"{100 * share:.1f} (")
    by_track = {(row[0], row[1]): row for row in track_rows(runs, config.presets)}
    assert sorted(by_track) == sorted((run["track"], run["look"]) for run in runs)
    for run in runs:
        row = by_track[(run["track"], run["look"])]
        assert row[TRACK_COLUMNS.index("scored steps")] == run["scored_steps"]
        share = 100 * run["covered_steps"] / run["scored_steps"]
        assert row[TRACK_COLUMNS.index("coverage [%] (95% band)")].startswith(f"{share:.1f} (")
        assert row[TRACK_COLUMNS.index("alarms [%]")] == pytest.approx(100 * run["alarm_rate"])


def test_faults_act_in_every_run_and_a_folder_keeps_to_its_own(tmp_path: Path, tiny_checkpoint):
    """A blackout for 1 s of the 2 s: a filter fed by a network doubts it on that half of
    the steps more (its frames are stale); one fed by the truth, which no blackout hides,
    never does."""
    checkpoint, _ = tiny_checkpoint(False)
    network = FilterConfig(
        kind="cbf", uncertainty="robust", state_source=f"learned:{checkpoint}", samples=3
    )
    faulty = short("pure-pursuit", safety=network, faults=("blackout:start=0.5,duration=1",))
    runs = run_robustness(faulty, tmp_path / "faulty", progress=False)
    clean = run_robustness(replace(faulty, faults=()), tmp_path / "clean", progress=False)
    for dark, light in zip(runs, clean, strict=True):
        assert dark["alarm_rate"] >= min(1.0, light["alarm_rate"] + 0.45)
    truth = replace(faulty, safety=FilterConfig(kind="cbf", uncertainty="robust"))
    assert all(run["alarm_rate"] == 0.0 for run in run_robustness(truth, tmp_path / "t", False))
    with pytest.raises(SafeRaceError, match=r"other settings.*faults"):
        run_robustness(faulty, tmp_path / "clean", progress=False)
    with pytest.raises(ConfigError, match="strat"):
        replace(faulty, faults=("blackout:strat=2",))
