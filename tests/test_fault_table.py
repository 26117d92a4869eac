"""The fault table (``saferace faults``): every fault at each severity for each driver,
without and behind the default filter, measured against the same driver fault-free; how far
a run got and when it drove on after a fault cleared; resumed, not rerun; and named on the
command line."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from saferace.errors import ConfigError
from saferace.eval.filters import FilterConfig
from saferace.experiments.fault_table import (
    DRIVE_ON_MPS,
    FAULT_START_S,
    distance_m,
    drive_on_s,
    planned_fault_runs,
    run_fault_table,
    table_faults,
)
from saferace.experiments.fault_table_config import FaultTableConfig
from saferace.faults.spec import FaultError, parse_fault
from tests.cli_helpers import run_cli


def test_every_fault_is_asked_for_at_each_severity_from_the_same_start():
    specs = table_faults(["blackout", "steering"], [1, 3])
    faults = [parse_fault(spec) for spec in specs]
    assert [(fault.name, fault.severity) for fault in faults] == [
        ("blackout", 1),
        ("blackout", 3),
        ("steering", 1),
        ("steering", 3),
    ]
    assert all(fault.start_s == FAULT_START_S for fault in faults)
    assert faults[1].duration_s == 2.0 and faults[3]["offset"] == 0.07  # the severity's sizes
    with pytest.raises(FaultError, match="unknown fault"):
        table_faults(["blackout", "sunburn"], [1])


def test_each_driver_runs_fault_free_beside_its_faults_behind_each_filter():
    filters = [FilterConfig(), FilterConfig(kind="cbf", state_source="generic")]
    runs = planned_fault_runs(["lab", "oval"], ["speeding", "expert"], ["a", "b"], filters)
    assert len(runs) == 2 * 2 * 2 * 3
    first = runs[:3]
    assert [run.fault for run in first] == ["", "a", "b"]
    assert {run.task for run in runs if run.driver == "speeding"} == {"RacingLine"}
    assert {run.task for run in runs if run.driver == "expert"} == {"CenterLine"}
    assert len({run.key for run in runs}) == len(runs)  # every run told apart


def recorded(speeds: list[float]) -> dict:
    """A result row of one step per speed (20 Hz, no thinning)."""
    return {"trajectory": {"v_x_mps": speeds}, "laps": [{"steps": len(speeds)}]}


def test_the_time_to_drive_on_counts_from_the_fault_clearing_to_moving_again():
    blackout = "blackout:start=1,duration=1"  # clears at 2 s, the 40th step's end
    stood = [3.0] * 30 + [0.0] * 16 + [2.0] * 14  # standing until 2.3 s, moving from 2.35 s
    assert drive_on_s(recorded(stood), blackout) == pytest.approx(0.35)
    assert drive_on_s(recorded([3.0] * 60), blackout) == 0.0  # never slowed
    assert math.isinf(drive_on_s(recorded([3.0] * 30 + [0.0] * 30), blackout))  # never again
    assert drive_on_s(recorded([3.0] * 30), blackout) is None  # the run ended first
    assert drive_on_s(recorded([3.0] * 60), "steering:start=1") is None  # it never clears
    assert DRIVE_ON_MPS < 2.0


def test_the_distance_driven_unwraps_over_the_lap():
    row = {"trajectory": {"s_m": [*(np.arange(90.0, 100.0, 0.5) % 100.0), 0.5, 3.0]}}
    assert distance_m(row, 100.0) == pytest.approx(13.0)
    assert distance_m({"trajectory": {"s_m": [4.0]}}, 100.0) == 0.0


def test_a_table_measures_the_faults_against_the_fault_free_run_and_resumes(
    quick_perception: Path, tmp_path: Path
):
    config = FaultTableConfig(
        tracks=("lab",),
        drivers=("expert",),
        faults=("blackout", "steering"),
        severities=(3,),
        seconds=6.0,
        state_source="generic:quick",
    )
    rows = run_fault_table(config, tmp_path, progress=False)
    assert len(rows) == 6
    assert {row["fault"] for row in rows} == {"", *table_faults(["blackout", "steering"], [3])}
    table = (tmp_path / "faults.md").read_text()
    assert all(f" {name} |" in table for name in ("blackout", "steering", "fault-free"))
    csv_lines = (tmp_path / "faults.csv").read_text().splitlines()
    assert len(csv_lines) == 1 + 6  # every run, the fault-free ones beside the faults
    free = [line for line in csv_lines if ",fault-free,-," in line]
    assert len(free) == 2 and all(",100.0," in line for line in free)  # its own measure
    assert (tmp_path / "faults.png").stat().st_size > 0
    again = run_fault_table(config, tmp_path, progress=False)  # nothing to run
    assert again == rows
    lines = (tmp_path / "runs.jsonl").read_text().splitlines()
    assert len(lines) == 6 and json.loads(lines[0])["fault"] == ""


def test_a_table_refuses_what_it_cannot_run():
    with pytest.raises(ConfigError, match="at least one"):
        FaultTableConfig(tracks=())
    with pytest.raises(ConfigError, match="twice"):
        FaultTableConfig(drivers=("drift", "drift"))
    with pytest.raises(ConfigError, match="at most 3"):
        FaultTableConfig(severities=(4,))
    with pytest.raises(ConfigError, match="generic"):
        FaultTableConfig(state_source="none")


def test_the_command_refuses_an_unknown_fault_and_driver_before_any_run(tmp_path: Path):
    unknown = run_cli("faults", "--tracks", "lab", "--faults", "sunburn")
    assert unknown.returncode == 2 and "sunburn" in unknown.stderr
    driver = run_cli("faults", "--drivers", "learned:missing.pt", "--out", str(tmp_path))
    assert driver.returncode != 0 and "no checkpoint at missing.pt" in driver.stderr
    assert not (tmp_path / "runs.jsonl").exists()
