"""Shift severities and the sweep's table and plot over uncertainty methods."""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path

import pytest

from saferace.cli import main
from saferace.envs.randomization import (
    SEVERITIES,
    VISUAL_PRESETS,
    RandomizationError,
    VisualRandomization,
    severity_randomization,
    visual_randomization,
)
from saferace.experiments.robustness import RUNS_FILE
from saferace.experiments.shift_sweep import SWEEP_COLUMNS, looks_of, sweep_rows


def test_severities_grow_from_the_built_look_through_strong():
    assert severity_randomization(0) == VisualRandomization()
    assert severity_randomization(3) == VISUAL_PRESETS["strong"]
    assert visual_randomization("severity-4") == severity_randomization(4)
    for field in fields(VisualRandomization):
        widths = []  # a probability of a change means nothing at level 0, where none is drawn
        for level in SEVERITIES[1:] if field.name.endswith("_probability") else SEVERITIES:
            value = getattr(severity_randomization(level), field.name)
            widths.append(value if isinstance(value, float) else value[1] - value[0])
        assert widths == sorted(widths), field.name  # never narrower at a higher level
    assert (
        severity_randomization(5).image_noise_std[1] > VISUAL_PRESETS["strong"].image_noise_std[1]
    )
    for bad in ("severity-6", "severity-x"):
        with pytest.raises(RandomizationError, match="severity"):
            visual_randomization(bad)


def run(look: str, covered: int, outside: float, **extra) -> dict:
    return {
        "track": "oval", "look": look, "seed": 0, "covered_steps": covered, "scored_steps": 100,
        "time_outside_lane_s": outside, "completion": 1.0, "lap_time_s": 6.0,
        "min_lane_barrier_m": 0.1 - outside, "alarm_rate": 0.0, **extra,
    }  # fmt: skip


def write_runs(folder: Path, runs: list[dict]) -> Path:
    folder.mkdir()
    (folder / RUNS_FILE).write_text("".join(json.dumps(r) + "\n" for r in runs))
    return folder


def test_the_sweep_tabulates_and_plots_each_method_by_severity(tmp_path: Path, capsys):
    honest = write_runs(
        tmp_path / "honest", [run("severity-0", 96, 0.0), run("severity-5", 94, 0.0)]
    )
    confident = write_runs(
        tmp_path / "confident",
        [
            run("severity-5", 20, 0.4, longest_standstill_s=3.5),
            run("severity-0", 60, 0.0, longest_standstill_s=0.0),
            run("severity-5", 10, 0.2, longest_standstill_s=1.0),
        ],
    )
    out = tmp_path / "sweep"
    assert (
        main(["shift-sweep", f"honest={honest}", f"confident={confident}", "--out", str(out)]) == 0
    )
    assert "confident" in capsys.readouterr().out
    assert (out / "shift_sweep.png").stat().st_size > 10_000
    methods = {
        label: [json.loads(line) for line in (folder / RUNS_FILE).open()]
        for label, folder in (("honest", honest), ("confident", confident))
    }
    assert looks_of(methods) == ["severity-0", "severity-5"]
    rows = {
        (row[0], row[1]): dict(zip(SWEEP_COLUMNS, row, strict=True)) for row in sweep_rows(methods)
    }
    shifted = rows[("confident", "severity-5")]
    assert shifted["coverage [%] (95% band)"].startswith("15.0 (")
    assert shifted["time outside lane [s]"] == pytest.approx(0.6) and shifted["runs outside"] == 2
    assert rows[("honest", "severity-5")]["runs outside"] == 0
    assert shifted["longest standstill [s]"] == 3.5  # the longer of its two runs'
    assert rows[("honest", "severity-5")]["longest standstill [s]"] == "-"  # not recorded
    with pytest.raises(SystemExit, match="2"):
        main(["shift-sweep", str(honest), "--out", str(out)])
    assert "LABEL=FOLDER" in capsys.readouterr().err
