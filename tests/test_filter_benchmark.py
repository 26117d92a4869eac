"""The filter protocol: a user's filter and perception from a fresh folder driven through a
small suite of the protocol's runs, resumed, on workers and on Ray; its submission
checked, doctored ones refused in one line, ranked on the filters' board and verified by
replay."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import run_cli

from saferace.errors import SafeRaceError
from saferace.eval.runner import file_sha256
from saferace.experiments import filter_benchmark
from saferace.experiments.filter_benchmark import FilterEntry, run_filter_benchmark
from saferace.experiments.filter_board import filter_board_html, filter_board_rows
from saferace.experiments.filter_submission_checks import check_filter_submission
from saferace.experiments.filter_suite import (
    FilterRunSpec,
    FilterSuite,
    load_filter_suite,
    scored_filter_run,
)
from saferace.experiments.verify import verify_submission
from saferace.track.random_track import write_random_track

#: A user's filter: brakes while the interval is within 0.25 m of an edge, and raises
#: among opponents (a bug of its own).
USERS_FILTER = """
import numpy as np


class SoftBrake:
    def __init__(self, setup):
        self.setup = setup

    def reset(self, seed=None):
        pass

    def certify(self, action, view):
        if len(view.opponents):
            raise RuntimeError("opponents were not expected")
        w_right, w_left = self.setup.track.widths(view.s_m)
        half = self.setup.car_half_width_m
        room = min(w_left - half - view.upper[0], w_right - half + view.lower[0])
        if room < 0.25 or view.in_doubt:
            brake = min(4.0, view.velocity[0] / 0.05)
            return np.array([-0.5 * view.mean[0] - view.mean[1], -brake])
        return action


def make(setup):
    return SoftBrake(setup)
"""
#: A user's perception: the road's grey pixels' centroid in the frame's lower half, with a
#: wide interval.
USERS_PERCEPTION = """
import numpy as np

from saferace.safety.uncertainty.perception import Perception


class Centroid:
    def __init__(self, setup):
        self.setup = setup

    def reset(self, seed=None):
        pass

    def perceive(self, image, velocity):
        lower = image[image.shape[0] // 2 :].astype(int)
        grey = (np.ptp(lower, axis=2) < 12) & (lower[..., 0] > 60) & (lower[..., 0] < 130)
        columns = np.nonzero(grey)[1]
        if columns.size == 0:
            return Perception(np.zeros(2), np.full(2, -1.0), np.full(2, 1.0), in_doubt=True)
        offset = columns.mean() / image.shape[1] - 0.5
        mean = np.array([-0.8 * offset, 0.0])
        return Perception(mean, mean - [0.3, 0.4], mean + [0.3, 0.4])


def make(setup):
    return Centroid(setup)
"""


@pytest.fixture(scope="module")
def users_folder(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A fresh folder with a filter and a perception method of the user's, the current one
    (for this module's tests)."""
    folder = tmp_path_factory.mktemp("mine")
    (folder / "soft_brake.py").write_text(USERS_FILTER)
    (folder / "centroid_eye.py").write_text(USERS_PERCEPTION)
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(folder)
        patch.setattr(sys, "path", [entry for entry in sys.path if entry not in ("", ".")])
        for module in ("soft_brake", "centroid_eye"):
            patch.delitem(sys.modules, module, raising=False)
        yield folder


def small_suite() -> FilterSuite:
    """Two drivers on ``lab`` under the true state and the perception, and among opponents
    under the true state: the protocol's runs, fewer."""
    suite = load_filter_suite()
    return dataclasses.replace(
        suite,
        drivers=("drift", "speeding"),
        tracks=("lab",),
        conditions={name: suite.conditions[name] for name in ("true", "perceived-2")},
        traffic_conditions=("true",),
    )


USERS_ENTRY = FilterEntry("soft_brake:make", "centroid_eye:make")


def without_timestamps(submission: dict) -> dict:
    return {k: v for k, v in submission.items() if k != "created"}


def test_the_protocol_is_fixed():
    suite = load_filter_suite()
    assert suite.version == 1
    assert suite.drivers == ("drift", "weave", "speeding", "expert")
    assert len(suite.tracks) == 6 and len(suite.circuits) == 3
    assert set(suite.expert_lap_time_s) == {*suite.tracks, *suite.circuits}
    assert len(suite.runs()) == len({run.key for run in suite.runs()}) == 216
    perceived = [name for name, c in suite.conditions.items() if c.state == "perceived"]
    assert [suite.conditions[name].look for name in perceived] == [0, 2, 4, 0, 0]


def test_safety_dominates_the_score():
    """The worst safe run outscores the best unsafe one: any time outside or a collision
    caused costs more than any loss of speed or any correction."""
    suite = load_filter_suite()
    lane = FilterRunSpec("expert", "lab", "true")
    traffic = FilterRunSpec("expert", "lab", "true", "braking")
    base = {"completion": 1.0, "driven_s": 30.0, "lap_time_s": None, "time_outside_lane_s": 0.0,
            "mean_steer_correction_rad": None, "mean_accel_correction_mps2": None}  # fmt: skip
    stood = scored_filter_run({**base, "completion": 0.0, "mean_steer_correction_rad": 1.0,
                               "mean_accel_correction_mps2": 9.0}, lane, suite)  # fmt: skip
    brushed = scored_filter_run({**base, "time_outside_lane_s": 0.05}, lane, suite)
    bumped = scored_filter_run({**base, "at_fault_collisions": 1}, traffic, suite)
    assert stood["safe"] and not brushed["safe"] and not bumped["safe"]
    assert stood["score"] == 0.5 > brushed["score"] and stood["score"] > bumped["score"]
    assert brushed["score"] == pytest.approx(0.5 * math.exp(-0.05))
    assert bumped["score"] == pytest.approx(0.5 * 0.6)
    lap_s = suite.expert_lap_time_s["lab"]
    fast = scored_filter_run({**base, "driven_s": lap_s, "lap_time_s": lap_s}, lane, suite)
    assert fast["score"] == pytest.approx(1.0) and fast["lap_time_ratio"] == 1.0
    raised = scored_filter_run({**base, "filter_error": "x raised"}, lane, suite)
    assert raised["score"] == 0.0
    faster = scored_filter_run({**base, "driven_s": lap_s / 2, "mean_steer_correction_rad": -1.0,
                                "mean_accel_correction_mps2": -1.0}, lane, suite)  # fmt: skip
    assert faster["score"] == pytest.approx(1.0)  # nothing scores above 1


@pytest.fixture(scope="module")
def users_submission(users_folder: Path) -> dict:
    return run_filter_benchmark(
        USERS_ENTRY, users_folder / "mine.json", progress=False, suite=small_suite()
    )


def test_a_users_filter_and_perception_run_the_protocol_from_their_folder(
    users_folder: Path, users_submission: dict
):
    rows = {row["key"]: row for row in users_submission["rows"]}
    assert len(rows) == 6
    traffic = [row for row in rows.values() if row["opponents"] is not None]
    assert traffic and all("opponents were not expected" in row["filter_error"] for row in traffic)
    assert all(row["score"] == 0.0 and row["driven_s"] == 0.05 for row in traffic)
    lane = [row for row in rows.values() if row["opponents"] is None]
    assert all(row["filter_error"] is None for row in lane)  # the rest went on
    assert all(row["time_outside_lane_s"] == 0.0 for row in lane if row["condition"] == "true")
    assert users_submission["filter_errors"] == len(traffic)
    files = users_submission["replay"]["files_sha256"]
    assert sorted(Path(path).name for path in files) == ["centroid_eye.py", "soft_brake.py"]
    checked = check_filter_submission(users_submission, "mine.json", small_suite())
    assert checked["score"] == pytest.approx(users_submission["score"])


def test_an_interrupted_run_goes_on_and_workers_and_ray_give_the_same_rows(
    users_folder: Path, users_submission: dict, monkeypatch: pytest.MonkeyPatch
):
    real_drive = filter_benchmark.drive_filter_run
    calls: list[FilterRunSpec] = []

    def interrupted(entry, spec, suite):
        calls.append(spec)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real_drive(entry, spec, suite)

    monkeypatch.setattr(filter_benchmark, "drive_filter_run", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_filter_benchmark(USERS_ENTRY, "cut.json", progress=False, suite=small_suite())
    driven: list[FilterRunSpec] = []
    monkeypatch.setattr(
        filter_benchmark,
        "drive_filter_run",
        lambda entry, spec, suite: driven.append(spec) or real_drive(entry, spec, suite),
    )
    resumed = run_filter_benchmark(USERS_ENTRY, "cut.json", progress=False, suite=small_suite())
    assert driven == small_suite().runs()[2:]  # nothing driven twice
    assert resumed["rows"] == users_submission["rows"]
    with pytest.raises(SafeRaceError, match="use another --out"):
        run_filter_benchmark(FilterEntry("none"), "cut.json", progress=False, suite=small_suite())
    monkeypatch.setattr(filter_benchmark, "drive_filter_run", real_drive)
    on_workers = run_filter_benchmark(
        USERS_ENTRY, "workers.json", workers=2, progress=False, suite=small_suite()
    )
    assert on_workers["rows"] == users_submission["rows"]


@pytest.mark.slow
def test_ray_gives_the_serial_rows(users_folder: Path, users_submission: dict):
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        on_ray = run_filter_benchmark(
            USERS_ENTRY, "ray.json", progress=False, suite=small_suite(), ray_address="local"
        )
    finally:
        ray.shutdown()
    assert on_ray["rows"] == users_submission["rows"]


def doctor_score(submission: dict) -> None:
    submission["rows"][1]["score"] += 0.1


def drop_a_run(submission: dict) -> None:
    del submission["rows"][2]


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        (doctor_score, "run speeding/lab/true: score is"),
        (lambda s: s.update(score=99.0), "mine.json: score is 99.0, recomputed"),
        (drop_a_run, "run drift/lab/perceived-2 of filter protocol v1 is missing"),
        (lambda s: s["rows"][0].update(time_outside_lane_s=-1.0), "time_outside_lane_s -1.0"),
        (lambda s: s["rows"][0].update(safe=False), "run drift/lab/true: safe is False"),
        (lambda s: s.update(entry="cbf fed generic"), "entry 'cbf fed generic' but replay"),
        (lambda s: s["replay"]["entry"].update(gains="paper"), "does not hash to its entry"),
        (
            lambda s: s["rows"][0].update(mean_steer_correction_rad=-3.6),
            "run drift/lab/true: mean_steer_correction_rad is -3.6",
        ),
        (lambda s: s["rows"][0].update(clipped_steps=True), "clipped_steps True is not 0 to"),
        (lambda s: s["rows"][-1].update(filter_error=None), "no termination and no filter error"),
        (lambda s: s["rows"][0].update(coverage=None), "run drift/lab/true: coverage is None"),
    ],
)
def test_doctored_submissions_are_refused_in_one_line_naming_run_and_field(
    users_submission: dict, change, reason: str
):
    bad = json.loads(json.dumps(users_submission))
    change(bad)
    with pytest.raises(SafeRaceError, match=r"^mine\.json") as refused:
        check_filter_submission(bad, "mine.json", small_suite())
    assert reason in str(refused.value) and "\n" not in str(refused.value)


def test_a_run_of_another_entry_pasted_in_is_refused(users_folder: Path, users_submission: dict):
    other = run_filter_benchmark(
        FilterEntry("none"), "none.json", progress=False, suite=small_suite(),
        runs=small_suite().runs()[:1],
    )  # fmt: skip
    pasted = json.loads(json.dumps(users_submission))
    pasted["rows"][0] = other["rows"][0]
    with pytest.raises(SafeRaceError, match="run drift/lab/true: driven by another entry"):
        check_filter_submission(pasted, "mine.json", small_suite())


def test_the_board_ranks_entries_and_verify_replays_them(
    users_folder: Path, users_submission: dict, monkeypatch: pytest.MonkeyPatch
):
    worse = json.loads(json.dumps(users_submission))
    worse["entry"], worse["score"] = "worse", users_submission["score"] / 2
    rows = filter_board_rows([worse, users_submission])
    assert [row[1] for row in rows] == [users_submission["entry"], "worse"]
    page = filter_board_html([worse, users_submission], small_suite())
    assert page.count("<tr>") == 3 and page.count("data:image/png;base64,") == 1
    monkeypatch.setattr(
        "saferace.experiments.verify.load_filter_suite", lambda version: small_suite()
    )
    monkeypatch.setattr(
        "saferace.experiments.filter_submission_checks.load_filter_suite",
        lambda version: small_suite(),
    )
    path = users_folder / "mine.json"
    passed = verify_submission(path, runs=2, progress=False, records=users_folder / "records")
    assert passed.passed and len(passed.replayed) == 2
    (users_folder / "soft_brake.py").write_text(USERS_FILTER + "\n# changed\n")
    try:
        with pytest.raises(SafeRaceError, match=r"soft_brake\.py changed since the runs"):
            verify_submission(path, runs=2, progress=False, records=users_folder / "records")
    finally:
        (users_folder / "soft_brake.py").write_text(USERS_FILTER)


def test_the_leaderboard_refuses_a_mix_of_boards(users_submission: dict, tmp_path: Path):
    filters = tmp_path / "filters.json"
    filters.write_text(json.dumps(users_submission))
    drivers = tmp_path / "drivers.json"
    drivers.write_text(json.dumps({"suite_version": 2}))
    result = run_cli("leaderboard", str(filters), str(drivers))
    assert result.returncode != 0
    assert "boards of their own" in result.stderr.strip().splitlines()[-1]


@pytest.mark.parametrize(
    ("options", "reason"),
    [
        (["--filter", "soft_brake:make", "--filter-gains", "paper"], "our filters' settings"),
        (["--filter", "cbf", "--faults", "blackout"], "no fault conditions"),
        (["--filter", "cbf", "--agent", "expert"], "not allowed with argument"),
        (["--filter", "cbff"], "MODULE:FACTORY"),
    ],
)
def test_a_filter_benchmark_of_bad_options_is_refused_in_one_line(
    users_folder: Path, options: list[str], reason: str
):
    result = run_cli("benchmark", *options, "--out", "refused.json")
    assert result.returncode != 0
    assert reason in result.stderr.strip().splitlines()[-1], result.stderr
    assert not Path("refused.json.runs.jsonl").exists()


def test_circuits_are_driven_only_from_a_folder_holding_the_files_the_protocol_pins(
    tmp_path: Path,
):
    circuit = write_random_track(tmp_path / "circuits" / "Loop_centerline.csv", 7)
    suite = dataclasses.replace(
        small_suite(),
        circuits={"Loop_centerline": file_sha256(circuit)},
        expert_lap_time_s={**small_suite().expert_lap_time_s, "Loop_centerline": 9.0},
    )
    assert len(suite.runs()) == 6  # no circuits without their folder
    with_circuits = suite.with_circuits(circuit.parent)
    added = with_circuits.runs()[6:]
    assert [run.key for run in added] == [
        f"{driver}/Loop_centerline/{condition}"
        for condition in suite.circuit_conditions
        for driver in suite.drivers
    ]
    assert with_circuits.track_argument("Loop_centerline") == str(circuit.resolve())
    with pytest.raises(SafeRaceError, match="no folder of circuits given"):
        suite.track_argument("Loop_centerline")
    with pytest.raises(SafeRaceError, match=r"circuit Loop_centerline: no .* \(give the folder"):
        suite.with_circuits(tmp_path)
    circuit.write_text(circuit.read_text() + "\n")
    with pytest.raises(SafeRaceError, match="is not the protocol's"):
        suite.with_circuits(circuit.parent)
