"""The benchmark protocol: suite, runs, resumption, workers, submissions and leaderboard."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from cli_helpers import run_cli

from saferace.errors import SafeRaceError
from saferace.experiments import benchmark
from saferace.experiments.benchmark import SUITE_VERSION, RunSpec, load_suite, run_benchmark
from saferace.experiments.benchmark_page import leaderboard_html, leaderboard_rows
from saferace.track import Track, builtin_track_names

LAB_RUNS = [RunSpec("lab", "CenterLine", 0, "none"), RunSpec("lab", "CenterLine", 1, "cbf")]


def without_timestamps(submission: dict) -> dict:
    return {k: v for k, v in submission.items() if k != "created"}


def test_the_suite_is_fixed_and_its_evaluation_tracks_are_nowhere_else():
    suite = load_suite()
    assert suite.version == SUITE_VERSION
    traffic = suite.traffic_set()
    assert len(suite.runs()) == 6 * 2 * 2 * 2 + 6 * len(traffic.opponents) * 1 * 2
    assert len({spec.key for spec in suite.runs()}) == len(suite.runs())
    evaluation = [t for t in suite.tracks if t not in builtin_track_names()]
    assert evaluation == ["eval_901", "eval_902"]
    for track in suite.tracks:
        Track.load(suite.track_argument(track))  # every track loads
        for task in suite.tasks:
            for seed in suite.seeds:
                assert suite.expert_lap_time_s[f"{track}/{task}/{seed}"] > 0.0
    repository = Path(__file__).resolve().parents[1]
    sources = [
        path
        for folder in ("saferace", "scripts", "benchmarks", "tests", "examples")
        for path in (repository / folder).rglob("*.py")
    ]
    users = sorted(path.name for path in sources if "901" in path.read_text())
    assert users == ["make_benchmark_suite.py", "test_benchmark.py"]  # nothing trains on them


def test_an_interrupted_benchmark_continues_to_the_same_submission(tmp_path: Path, monkeypatch):
    whole = run_benchmark("pure-pursuit", tmp_path / "whole.json", progress=False, runs=LAB_RUNS)
    real_drive = benchmark.drive_run
    calls = []

    def interrupted(agent, spec, suite, mc_samples=10, faults=()):
        calls.append(spec)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_drive(agent, spec, suite, mc_samples, faults)

    monkeypatch.setattr(benchmark, "drive_run", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_benchmark("pure-pursuit", tmp_path / "cut.json", progress=False, runs=LAB_RUNS)
    assert not (tmp_path / "cut.json").exists()
    driven = []

    def counted(agent, spec, suite, mc_samples=10, faults=()):
        driven.append(spec)
        return real_drive(agent, spec, suite, mc_samples, faults)

    monkeypatch.setattr(benchmark, "drive_run", counted)
    resumed = run_benchmark("pure-pursuit", tmp_path / "cut.json", progress=False, runs=LAB_RUNS)
    assert without_timestamps(resumed) == without_timestamps(whole)
    assert driven == [calls[1]]  # only the run the interrupt cut: the first one was kept
    with pytest.raises(SafeRaceError, match="use another --out"):
        run_benchmark("expert", tmp_path / "cut.json", progress=False, runs=LAB_RUNS)


def test_a_run_s_score_worked_by_hand():
    """Half a lap in 10 s where the expert laps lab in its reference time, 1.3 s outside,
    then the same with two collisions it caused: each factor of the score by hand."""
    suite = benchmark.load_suite()
    spec = next(run for run in suite.runs() if run.track == "lab" and run.opponents is None)
    expert_s = suite.expert_lap_time_s[suite.reference_key(spec)]
    measured = {"completion": 0.5, "driven_s": 10.0, "lap_time_s": None,
                "time_outside_lane_s": 1.3, "at_fault_collisions": 0}  # fmt: skip
    row = benchmark.scored(measured, spec, suite)
    speed_ratio = 0.5 * suite.laps_of(spec) * expert_s / 10.0
    assert row["speed_ratio"] == pytest.approx(speed_ratio, rel=1e-12)
    assert row["score"] == pytest.approx(0.5 * speed_ratio * math.exp(-1.3), rel=1e-12)
    assert row["lap_time_ratio"] is None
    traffic = next(run for run in suite.runs() if run.opponents is not None)
    expert_traffic_s = suite.expert_lap_time_s[suite.reference_key(traffic)]
    collided = benchmark.scored({**measured, "at_fault_collisions": 2}, traffic, suite)
    alone = 0.5 * (0.5 * suite.laps_of(traffic) * expert_traffic_s / 10.0) * math.exp(-1.3)
    assert collided["score"] == pytest.approx(alone * 0.6**2, rel=1e-12)  # 0.6 a collision


def test_rows_scores_and_workers(tmp_path: Path):
    serial = run_benchmark("pure-pursuit", tmp_path / "a.json", progress=False, runs=LAB_RUNS)
    parallel = run_benchmark(
        "pure-pursuit", tmp_path / "b.json", workers=2, progress=False, runs=LAB_RUNS
    )
    assert parallel["rows"] == serial["rows"]  # the same runs, whatever the order they end in
    plain, filtered = serial["rows"]
    assert plain["filter"] == "none" and filtered["filter"] == "cbf"
    for row in serial["rows"]:
        assert row["completion"] == 1.0 and row["laps_completed"] == 1
        assert 0.5 < row["lap_time_ratio"] < 2.0
        expected = row["completion"] * row["speed_ratio"] * math.exp(-row["time_outside_lane_s"])
        assert row["score"] == pytest.approx(expected)
        assert row["longest_standstill_s"] == 0.0  # reported beside the score, not in it
        assert benchmark.run_words(row).endswith(", longest standstill 0.00 s")
    assert serial["score"] == pytest.approx(100.0 * plain["score"])  # the filter cannot lift it
    assert serial["score_with_filter"] == pytest.approx(100.0 * filtered["score"])
    assert 0.0 <= serial["intervention_rate"] <= 1.0


@pytest.fixture(scope="module")
def submission(honest_submission: Path) -> dict:
    return json.loads(honest_submission.read_text())


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        (lambda s: s.pop("score"), "missing field(s) score"),
        (lambda s: s.update(suite_version=SUITE_VERSION + 1), "does not ship (it scores v1 to"),
        (lambda s: s.update(score=float("nan")), "score is nan, not a finite number"),
        (lambda s: s["rows"][0].pop("completion"), "row 0 lacks completion"),
        (lambda s: s.update(rows=[]), "no rows"),
        (lambda s: s.update(score=150.0), "score is 150.0, recomputed"),
    ],
)
def test_bad_submissions_are_refused_in_one_line(
    submission: dict, tmp_path: Path, change, reason: str
):
    bad = json.loads(json.dumps(submission))
    change(bad)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(bad))
    result = run_cli("leaderboard", str(path))
    assert result.returncode != 0
    message = result.stderr.strip().splitlines()
    assert len(message) == 1 and reason in message[0], result.stderr


def test_leaderboard_page_ranks_and_embeds_the_paths(submission: dict, tmp_path: Path):
    worse = json.loads(json.dumps(submission))
    worse["agent"], worse["score"] = "slower", submission["score"] / 2
    rows = leaderboard_rows([worse, submission])
    assert [row[1] for row in rows] == ["pure-pursuit", "slower"]
    page = leaderboard_html([worse, submission], load_suite())
    assert page.count("<tr>") == 3  # header and two agents
    assert page.count("data:image/png;base64,") == len(load_suite().tracks)
    assert "addEventListener" in page
    path = tmp_path / "submission.json"
    path.write_text(json.dumps(submission))
    result = run_cli("leaderboard", str(path), "--html", str(tmp_path / "board.html"))
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "board.html").stat().st_size > 10_000


@pytest.fixture(scope="module")
def local_ray():
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_ray_gives_the_serial_rows_and_reports_failed_runs(tmp_path: Path, local_ray):
    serial = run_benchmark("pure-pursuit", tmp_path / "a.json", progress=False, runs=LAB_RUNS)
    on_ray = run_benchmark(
        "pure-pursuit", tmp_path / "b.json", progress=False, runs=LAB_RUNS, ray_address="local"
    )
    assert on_ray["rows"] == serial["rows"]
    with pytest.raises(SafeRaceError, match=r"2 run\(s\) failed on Ray after 2 retries"):
        run_benchmark(
            "saferace.eval.agents:no_such_factory", tmp_path / "c.json", progress=False,
            runs=LAB_RUNS, ray_address="local",
        )  # fmt: skip
    assert not (tmp_path / "c.json").exists()


def test_failed_runs_in_worker_processes_are_reported_not_dropped(tmp_path: Path):
    with pytest.raises(SafeRaceError, match=r"2 run\(s\) failed in worker processes"):
        run_benchmark(
            "saferace.eval.agents:no_such_factory",
            tmp_path / "c.json",
            workers=2,
            progress=False,
            runs=LAB_RUNS,
        )


@pytest.mark.parametrize(
    ("count", "words"),
    [(0, "0 at-fault collisions"), (1, "1 at-fault collision"), (3, "3 at-fault collisions")],
)
def test_a_runs_line_counts_its_collisions_in_good_english(count: int, words: str):
    row = {
        "score": 0.5,
        "completion": 1.0,
        "time_outside_lane_s": 0.0,
        "at_fault_collisions": count,
    }
    assert benchmark.run_words(row).endswith(f", longest standstill -, {words}")


BENT = ("steering:offset=0.07",)  # the servo's centre 4 degrees off, from the start


def test_a_benchmark_under_faults_drives_verifies_and_ranks_with_them(
    submission: dict, tmp_path: Path
):
    from saferace.experiments.verify import choose_runs, verify_submission

    bent = run_benchmark(
        "pure-pursuit", tmp_path / "bent.json", progress=False, runs=LAB_RUNS[:1], faults=BENT
    )
    [faulted] = bent["rows"]
    keys = [row["key"] for row in submission["rows"]]
    clean = submission["rows"][keys.index(faulted["key"])]
    assert faulted["mean_abs_deviation_m"] > clean["mean_abs_deviation_m"] + 0.02  # it bites
    replay = bent["replay"]
    assert replay["faults"] == ["steering:severity=2,start=0,duration=inf,offset=0.07"]
    assert replay["agent_sha256"] != submission["replay"]["agent_sha256"]
    with pytest.raises(SafeRaceError, match="use another --out"):
        run_benchmark("pure-pursuit", tmp_path / "bent.json", progress=False, runs=LAB_RUNS[:1])
    whole = json.loads(json.dumps(submission))  # the fault-free rows stand in for the others
    for row in whole["rows"]:
        row["agent_sha256"] = replay["agent_sha256"]
    whole["rows"][keys.index(faulted["key"])] = faulted
    whole["replay"] = replay
    whole.update(benchmark.totals(whole["rows"], load_suite()))
    path = tmp_path / "whole.json"
    path.write_text(json.dumps(whole))
    seed = next(seed for seed in range(1000) if choose_runs(keys, 1, seed) == [faulted["key"]])
    records = tmp_path / "records"
    assert verify_submission(path, runs=1, seed=seed, progress=False, records=records).passed
    rows = leaderboard_rows([whole, submission])
    assert [(row[0], row[2]) for row in rows] == [(1, "v2"), (1, f"v2 under {replay['faults'][0]}")]
    whole["replay"] = {**replay, "faults": []}  # the faults taken out of the record
    path.write_text(json.dumps(whole))
    with pytest.raises(SafeRaceError, match="replay faults must be a list of one or more"):
        verify_submission(path, runs=1, seed=seed, progress=False, records=records)
    whole["replay"].pop("faults")
    path.write_text(json.dumps(whole))
    with pytest.raises(SafeRaceError, match="does not hash to its agent_sha256"):
        verify_submission(path, runs=1, seed=seed, progress=False, records=records)
