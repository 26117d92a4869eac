"""The paper's tables from one command: a tiny preset end to end and the quick one (both
slow: the tiny one's runs take a minute), and the tables and claims from rows."""

from __future__ import annotations

import csv
import json
from dataclasses import replace
from pathlib import Path

import pytest
from cli_helpers import run_cli
from rerun.chunk import RrdReader

from saferace.cli import main
from saferace.experiments.paper import Preset, run_paper_tables
from saferace.experiments.paper.presets import (
    PERCEPTION_MODES,
    RUN_KINDS,
    RUN_LABELS,
    TABLE_2_MONO,
    dagger_config,
    run_config,
)
from saferace.experiments.paper.report import (
    CELL_NAMES,
    VERDICT_COLUMNS,
    claims,
    table_lines,
    verdicts,
)
from saferace.experiments.paper.runs import from_1_name, run_dir
from saferace.learning.checkpoint import CONFORMAL_KEY, load_checkpoint
from saferace.learning.run_layout import RunLayout
from saferace.names import TASKS

#: Two iterations of 3 s drives on the mono camera, the fork filtered in iteration 2 (the
#: generic one fed the quick recipe's model); frames past 0.2 of the lap (reached within the
#: 3 s) are held out to calibrate the state network.
TINY = Preset(
    name="tiny",
    settings=(replace(TABLE_2_MONO, filter_from={"CenterLine": 1, "RacingLine": 1}),),
    iterations=2,
    epochs=1,
    min_train_steps=4,
    train_fraction=0.2,
    max_seconds=3.0,
    mc_samples=3,
    unseen_tracks=("oval",),
    perception="generic:quick",
)
SETTING = TINY.settings[0]


# The tiny preset's runs take a minute: the tests that read them are in the slow suite (the
# default suite stays within 15 min on 2 cores); the tables and claims from hand-made rows
# are not.
@pytest.fixture(scope="module")
def tables(tmp_path_factory: pytest.TempPathFactory, quick_perception) -> tuple[Path, list[Path]]:
    out = tmp_path_factory.mktemp("paper")
    return out, run_paper_tables(TINY, [0], out, progress=False)


def metrics(out: Path, task: str, kind: str) -> list[dict]:
    path = run_dir(out, SETTING, task, 0, kind) / "metrics.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.mark.slow
def test_every_output_is_written(tables):
    _, written = tables
    names = {path.name for path in written}
    assert names == {
        "table2.md",
        "table2.csv",
        "table2_trajectories.png",
        "table2_final_filtered_racingline.rrd",
        "unseen_tracks.md",
        "timings.md",
    }
    assert all(path.stat().st_size > 0 for path in written)


@pytest.mark.slow
def test_the_table_has_the_papers_layout_and_the_runs_numbers(tables):
    out, _ = tables
    with open(out / "table2.csv") as handle:
        header, *lines = list(csv.reader(handle))
    assert header[:2] == ["iteration", "filter"]
    assert len(header) == 2 + len(TASKS) * len(CELL_NAMES)
    assert [line[:2] for line in lines] == [
        ["0", "none"],
        ["1", "none"],
        ["2", "none"],
        ["2", "perceived"],
        ["2", "perceived, conformal"],
        ["2", "perceived, generic"],
        ["2", "true state"],
    ]
    columns = {
        "lap [s]": "duration_s",  # 3 s drives: each cell is the time driven, starred
        "mean dev [m]": "mean_abs_deviation_m",
        "outside [s]": "time_outside_lane_s",
    }
    for line, (kind, _, _) in zip(lines[2:], RUN_KINDS, strict=True):
        for group, task in enumerate(TASKS):
            row = metrics(out, task, kind)[2]
            for cell, key in columns.items():
                text = line[2 + group * len(CELL_NAMES) + CELL_NAMES.index(cell)]
                assert float(text.rstrip("*")) == pytest.approx(row[key], rel=1e-2, abs=1e-9)
    text = (out / "table2.md").read_text()
    claims = [line for line in text.splitlines() if line.startswith("- ")]
    assert len(claims) == len(TASKS) * (len(RUN_KINDS) + len(PERCEPTION_MODES))
    filtered_runs = len(TASKS) * (len(RUN_KINDS) - 1)
    assert sum("lane exits in filtered iterations" in claim for claim in claims) == filtered_runs
    assert sum("laps completed in iterations 2-2: " in claim for claim in claims) == filtered_runs
    for task in TASKS:  # iteration 1 again, behind each mode's filter: a fork with k = 0
        unfiltered = metrics(out, task, "none")[1]
        assert not unfiltered["filtered"]
        for kind in PERCEPTION_MODES:
            first = metrics(out, task, from_1_name(kind))[1]
            assert first["filtered"] and first["intervention_rate"] is not None
            start = f"- {task}, seed 0, iteration 1 behind the filter fed the {RUN_LABELS[kind]} "
            (claim,) = [line for line in claims if line.startswith(start)]
            for row in (first, unfiltered):
                assert f"{row['time_outside_lane_s']:.2f} s outside the lane" in claim


@pytest.mark.slow
def test_the_claims_are_judged_for_both_perception_modes(tables):
    out, _ = tables
    text = (out / "table2.md").read_text()
    verdicts = text.split("## The paper's claims, by perception mode")[1].split("## Claims")[0]
    lines = [line for line in verdicts.splitlines() if line.startswith("| ")][1:]
    assert len(lines) == len(TASKS) * len(PERCEPTION_MODES)
    for line in lines:
        task, _, mode, filtered, with_filter, without, inside, standstill, sooner = (
            cell.strip() for cell in line.strip("|").split("|")
        )
        kind = next(kind for kind in PERCEPTION_MODES if RUN_LABELS[kind] == mode)
        first, run = metrics(out, task, from_1_name(kind))[1], metrics(out, task, kind)
        assert filtered == "1, 2 (k = 1)"
        exits = [str(row["iteration"]) for row in (first, run[2]) if row["time_outside_lane_s"]]
        assert inside == ("holds" if not exits else "fails: iteration " + ", ".join(exits))
        longest = max(row["longest_standstill_s"] for row in (first, run[2]))
        assert float(standstill) == pytest.approx(longest, rel=1e-2, abs=1e-9)
        lapped = [row["iteration"] for row in (first, *run[1:]) if row["completed"]]
        assert with_filter == (str(min(lapped)) if lapped else "-")
        unfiltered = [r["iteration"] for r in metrics(out, task, "none")[1:] if r["completed"]]
        assert without == (str(min(unfiltered)) if unfiltered else "-")
        if not lapped and not unfiltered:
            assert sooner == "neither lapped"


def metric_row(iteration: int, filtered: bool, completed: bool, standstill_s: float | None):
    """A DAgger metrics row as the tables read it (``standstill_s`` None: written before
    the longest standstill was recorded); never outside the lane."""
    row = {
        "iteration": iteration, "filtered": filtered, "completed": completed,
        "lap_time_s": 9.0 if completed else None, "duration_s": 9.0 if completed else 30.0,
        "mean_abs_deviation_m": 0.05, "time_outside_lane_s": 0.0,
        "intervention_rate": 0.3 if filtered else None, "held_out_mean_abs_deviation_m": None,
        "held_out_time_outside_lane_s": None,
    }  # fmt: skip
    return row if standstill_s is None else {**row, "longest_standstill_s": standstill_s}


def test_a_filtered_run_held_still_inside_the_lane_shows_in_the_tables_and_claims():
    """Never leaving the lane by standing still while the driver asks to go is no success:
    the table, the verdicts and the claims show the standstill beside the lane verdict."""
    setting = replace(SETTING, filter_from={"CenterLine": 1, "RacingLine": 1})
    shared = [metric_row(0, False, True, 0.0), metric_row(1, False, False, 0.5)]
    rows = {
        ("CenterLine", 0, "none"): [*shared, metric_row(2, False, True, 0.0)],
        ("CenterLine", 0, "cbf"): [*shared, metric_row(2, True, False, 30.0)],
    }
    from_1 = {("CenterLine", 0, "cbf"): metric_row(1, True, False, 12.0)}
    lines = table_lines(setting, rows, [0])
    assert [line[:2] for line in lines] == [[0, "none"], [1, "none"], [2, "none"], [2, "perceived"]]
    cell = 2 + CELL_NAMES.index("longest standstill [s]")  # CenterLine's group
    assert [line[cell] for line in lines] == ["0", "0.5", "0", "30"]
    (verdict,) = verdicts(setting, rows, from_1)
    verdict = dict(zip(VERDICT_COLUMNS, verdict, strict=True))
    assert verdict["never leaves the lane"] == "holds"
    assert verdict["longest standstill, filtered [s]"] == "30"  # of iterations 1 and 2
    said = claims(setting, rows, from_1)
    assert "longest standstill in filtered iterations: 30.00 s" in said[1]
    assert said[2].endswith("did not lap, 0.00 s outside the lane, longest standstill 0.50 s")
    assert (
        "behind the filter fed the perceived state (a fork with k = 0): did not lap, 0.00 s "
        "outside the lane, longest standstill 12.00 s;" in said[2]
    )
    older = {key: [{k: v for k, v in row.items() if k != "longest_standstill_s"} for row in runs]
             for key, runs in rows.items()}  # fmt: skip
    assert table_lines(setting, older, [0])[3][cell] == "-"
    (verdict,) = verdicts(setting, older, from_1)
    assert verdict[VERDICT_COLUMNS.index("longest standstill, filtered [s]")] == "-"
    assert (
        "longest standstill in filtered iterations: not recorded"
        in claims(setting, older, from_1)[1]
    )


@pytest.mark.slow
def test_the_forks_share_the_unfiltered_iterations(tables):
    out, _ = tables
    for task in TASKS:
        unfiltered = metrics(out, task, "none")
        for kind in ("cbf", "robust", "generic", "oracle"):
            forked = metrics(out, task, kind)
            assert forked[:2] == unfiltered[:2]
            assert forked[2]["filtered"] and not unfiltered[2]["filtered"]
        # only the robust fork's networks carry a conformal calibration, fitted for its drive
        calibrated = {
            kind: CONFORMAL_KEY
            in load_checkpoint(
                RunLayout(run_dir(out, SETTING, task, 0, kind)).checkpoint(2)
            ).metadata
            for kind in ("none", "cbf", "robust")
        }
        assert calibrated == {"none": False, "cbf": False, "robust": True}


@pytest.mark.slow
def test_unseen_tracks_timings_and_the_recording(tables):
    out, _ = tables
    unseen = [
        line
        for line in (out / "unseen_tracks.md").read_text().splitlines()
        if line.startswith("| table2")
    ]
    # The forks drive iteration 2 with the unfiltered run's networks: one policy per line,
    # scored without the filter, behind the paper's, the robust conformal and the generic one.
    assert len(unseen) == len(TASKS) * 4
    assert all(line.split("|")[4].strip() == "final of none run" for line in unseen)
    filters = [line.split("|")[6].strip() for line in unseen]
    kinds = ["none", "perceived state", "perceived, conformal", "perceived, generic"]
    assert sorted(filters) == sorted(kinds * 2)
    assert all(line.split("|")[5].strip() == "oval" for line in unseen)
    seconds = {
        line.split("|")[1].strip(): float(line.split("|")[2])
        for line in (out / "timings.md").read_text().splitlines()[4:]
    }
    assert set(seconds) == {"collection", "training", "unseen tracks", "recording"}
    assert all(value > 0 for value in seconds.values())
    recording = out / "table2_final_filtered_racingline.rrd"
    entities = {str(path) for path in RrdReader(recording).store().schema().entity_paths()}
    assert {"/filter/kappa_radpm/believed", "/filter/accel_mps2/filtered"} <= entities


@pytest.mark.slow
def test_a_second_call_resumes_and_redoes_nothing(tables):
    out, _ = tables
    runs = [(task, kind) for task in TASKS for kind, _, _ in RUN_KINDS]
    stored = sorted(out.glob("table2/*/seed0/*/*/*"))  # rounds and checkpoints
    before = {run: metrics(out, *run) for run in runs}, {p: p.stat().st_mtime_ns for p in stored}
    run_paper_tables(TINY, [0], out, progress=False)
    after = {run: metrics(out, *run) for run in runs}, {p: p.stat().st_mtime_ns for p in stored}
    assert after == before


@pytest.mark.slow
def test_quick_preset_end_to_end(tmp_path: Path):
    result = run_cli("paper-tables", "--preset", "quick", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    assert "# Table 2" in result.stdout
    text = (tmp_path / "table2.md").read_text()
    assert "perceived" in text and "true state" in text
    rows = metrics(tmp_path, "CenterLine", "none")
    assert rows[0]["completed"] and rows[0]["time_outside_lane_s"] == 0.0  # the expert
    assert (tmp_path / "table2_trajectories.png").stat().st_size > 50_000


def test_the_state_uncertainty_and_slack_reach_every_run(monkeypatch, tmp_path: Path):
    import saferace.experiments.paper as paper

    called = {}
    monkeypatch.setattr(
        paper, "run_paper_tables", lambda preset, seeds, out: called.update(preset=preset) or []
    )
    arguments = ["--state-uncertainty", "ensemble", "--filter-slack", "l1", "--out", str(tmp_path)]
    assert main(["paper-tables", *arguments]) == 0
    preset = called["preset"]
    assert preset.name == "quick" and preset.state_uncertainty == "ensemble"
    for kind, _, _ in RUN_KINDS:
        config = run_config(dagger_config(preset, preset.settings[0], "CenterLine", 0), kind)
        assert config.training.state_uncertainty == "ensemble"
        assert config.filter.slack == "l1"
        robust = kind in ("robust", "generic")
        assert config.filter.uncertainty == ("robust" if robust else "chance")
        assert config.calibrate_spread == (not robust)
        assert config.filter.state_source == {"generic": "generic", "oracle": None}.get(
            kind, "learned"
        )
