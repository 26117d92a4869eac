"""A doctored submission is refused, naming what is wrong; an honest one passes unchanged;
``saferace verify`` replays runs and finds edited rows and swapped agent files."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from cli_helpers import run_cli

from saferace.envs.drivetrain import DrivetrainParams
from saferace.errors import SafeRaceError
from saferace.eval.runner import file_sha256
from saferace.experiments.benchmark import (
    TRAFFIC_MEASUREMENTS,
    TRAJECTORY_POINTS,
    RunSpec,
    load_suite,
    scored,
    totals,
)
from saferace.experiments.benchmark_page import COLUMNS, leaderboard_html, leaderboard_rows
from saferace.experiments.replay_record import replay_record
from saferace.experiments.submission_checks import CONTROL_DT_S, check_submission
from saferace.experiments.verify import (
    choose_runs,
    replay_compiled,
    replay_device,
    verification_record,
    verify_submission,
)
from saferace.names import COMPILE_VARIABLE
from saferace.track import Track

SOURCE = "sub.json"
FIRST = "lab/CenterLine/0/none"  # the suite's first run: a finished lap, no filter


@pytest.fixture
def honest(honest_submission: Path) -> dict:
    return json.loads(honest_submission.read_text())


def first_row(data: dict) -> dict:
    return data["rows"][0]


def halve_every_lap_time(data: dict) -> None:
    for row in data["rows"]:
        row["lap_time_s"] /= 2


def flag_an_exit(data: dict) -> None:
    first_row(data)["trajectory"]["outside"][5] = True  # and time outside left at 0


def scale_the_path(data: dict, factor: float) -> None:
    trajectory = first_row(data)["trajectory"]
    trajectory["x_m"] = [factor * x for x in trajectory["x_m"]]
    trajectory["y_m"] = [factor * y for y in trajectory["y_m"]]


def stand_still(data: dict) -> None:
    trajectory = first_row(data)["trajectory"]
    count = len(trajectory["x_m"])
    trajectory["x_m"], trajectory["y_m"] = (
        [trajectory["x_m"][0]] * count,
        [trajectory["y_m"][0]] * count,
    )


def shift_the_path(data: dict) -> None:
    trajectory = first_row(data)["trajectory"]
    trajectory["x_m"] = [x + 5.0 for x in trajectory["x_m"]]


def drop_half_the_points(data: dict) -> None:
    trajectory = first_row(data)["trajectory"]
    for name in ("x_m", "y_m", "outside"):
        trajectory[name] = trajectory[name][::2]


def traffic_row(data: dict) -> dict:
    """The submission's first run in traffic."""
    return next(row for row in data["rows"] if row.get("opponents") is not None)


def hide_a_collision(data: dict) -> None:
    """A run that caused a collision, submitted with its score as if it had not."""
    row = traffic_row(data)
    row["collisions"] += 1
    row["at_fault_collisions"] += 1


def set_row(**values):
    return lambda data: first_row(data).update(values)


def stand(row: dict, steps: int, completion: float = 0.0) -> dict:
    """``row`` made a drive of ``steps`` control steps that never left its first point
    and never left the lane: the shape of a car that stalled at the start."""
    stride = max(1, steps // TRAJECTORY_POINTS)
    points = -(-steps // stride)
    x_m, y_m = row["trajectory"]["x_m"][0], row["trajectory"]["y_m"][0]
    row.update(
        driven_s=steps * CONTROL_DT_S,
        completion=completion,
        laps_completed=0,
        lap_time_s=None,
        time_outside_lane_s=0.0,
        trajectory={"x_m": [x_m] * points, "y_m": [y_m] * points, "outside": [False] * points},
    )
    return row


def jump(row: dict, metres: float) -> dict:
    """``row``'s path, from its second point on, moved ``metres`` along x."""
    trajectory = row["trajectory"]
    trajectory["x_m"] = trajectory["x_m"][:1] + [x + metres for x in trajectory["x_m"][1:]]
    return row


def outside_at(row: dict, points: int, seconds: float) -> dict:
    """``row`` flagged outside at its first ``points`` points, for ``seconds`` in all."""
    flags = row["trajectory"]["outside"]
    flags[:points] = [True] * points
    row["time_outside_lane_s"] = seconds
    return row


def lap_length_m(row: dict) -> float:
    return Track.load(load_suite().track_argument(row["track"])).length_m


#: A jump between two trajectory points at the car's top speed, one control step apart.
TOP_SPEED_STEP_M = DrivetrainParams().top_speed_mps * CONTROL_DT_S


def leave_the_second_lap_undriven(data: dict) -> None:
    """A traffic run's trajectory after its first lap held at the first lap's end."""
    trajectory = traffic_row(data)["trajectory"]
    half = len(trajectory["x_m"]) // 2
    for name in ("x_m", "y_m"):
        trajectory[name][half:] = [trajectory[name][half]] * (len(trajectory[name]) - half)


def start_elsewhere(data: dict) -> None:
    """A minute's stall whose first point lies 1.5 m off the start, a reach its next point
    (0.3 s later) could make at top speed."""
    trajectory = stand(first_row(data), 1200)["trajectory"]
    trajectory["x_m"][0] += 1.5


def double_a_traffic_lap_time(data: dict) -> None:
    traffic_row(data)["lap_time_s"] *= 2


REFUSALS = {
    "a doctored score": (lambda d: d.update(score=150.0), "sub.json: score is 150.0, recomputed"),
    "a doctored run score": (set_row(score=1.0), f"run {FIRST}: score is 1.0, recomputed"),
    "a doctored ratio": (set_row(lap_time_ratio=0.5), "lap_time_ratio is 0.5, recomputed"),
    "a doctored reference": (
        set_row(expert_lap_time_s=3.0),
        "expert_lap_time_s is 3.0, recomputed 7.7782",
    ),
    "lap times halved": (halve_every_lap_time, f"run {FIRST}: the drive ("),
    "completion above 1": (set_row(completion=1.2), "completion 1.2 is outside [0, 1]"),
    "completion below a finished lap": (
        set_row(completion=0.9),
        "every lap completed but completion is 0.9",
    ),
    "a lap time without a lap": (set_row(laps_completed=0), "without a completed lap"),
    "time outside hidden": (flag_an_exit, "disagrees with the trajectory, outside at 1"),
    "more time outside than driven": (set_row(time_outside_lane_s=99.0), "is not within the"),
    "a standstill longer than the drive": (
        set_row(longest_standstill_s=99.0),
        "longest_standstill_s 99.0 is not within the",
    ),
    "a standstill below zero": (set_row(longest_standstill_s=-0.05), "longest_standstill_s -0.05"),
    "a drive longer than the suite's": (set_row(driven_s=61.0), "driven_s 61.0 is not 1 to 60 s"),
    "a drive between control steps": (set_row(driven_s=7.81), "driven_s 7.81 is not 1 to 60 s"),
    "a drive of no time": (set_row(driven_s=0.0), "driven_s 0.0 is not 1 to 60 s"),
    "a path faster than the car": (lambda d: scale_the_path(d, 3.0), "faster than the car's"),
    "a path elsewhere": (shift_the_path, "does not start at the run's start"),
    "a first point elsewhere": (start_elsewhere, "does not start at the run's start"),
    "a jump 3 mm faster than the car": (
        lambda d: jump(stand(first_row(d), 10), TOP_SPEED_STEP_M + 0.003),
        "faster than the car's top speed",
    ),
    "a path too short for its completion": (
        lambda d: jump(stand(first_row(d), 10, 3.0 / lap_length_m(first_row(d))), 0.3),
        "the trajectory is 0.3 m long, 0.10 times the 3.0 m",
    ),
    "a second lap never driven": (leave_the_second_lap_undriven, "times the "),
    "a traffic lap time doubled": (double_a_traffic_lap_time, "is longer than the drive"),
    "time outside overstated": (
        lambda d: outside_at(stand(first_row(d), 10), 2, 0.15),
        "time_outside_lane_s 0.15 disagrees with the trajectory, outside at 2 of its points",
    ),
    "a path that stands still": (stand_still, "the trajectory is 0.0 m long"),
    "a thinned path": (drop_half_the_points, "points, "),
    "an intervention without a filter": (set_row(intervention_rate=0.5), "without a filter"),
    "a missing run": (
        lambda d: d["rows"].pop(),
        "eval_902/Overtake/0/cbf/braking of suite v2 is missing",
    ),
    "a duplicated run": (lambda d: d["rows"].append(d["rows"][0]), f"run {FIRST} appears 2 times"),
    "a run of another track": (set_row(track="bean"), "bean/CenterLine/0/none is not a run of"),
    "a run of another suite version": (set_row(suite_version=3), "of suite v3, not v2"),
    "a run of another agent": (set_row(agent_sha256="0" * 64), "driven by another agent"),
    "a drive too long for a float": (set_row(driven_s=10**400), "driven_s is 1000"),
    "coordinates as text": (
        lambda d: first_row(d)["trajectory"]["x_m"].__setitem__(0, "1.5"),
        "trajectory points are not finite numbers",
    ),
    "a deviation as text": (set_row(mean_abs_deviation_m="0.1"), "mean_abs_deviation_m is '0.1'"),
    "a score as text": (lambda d: d.update(score="66.5"), "score is '66.5', not a finite number"),
    "a suite version of true": (
        lambda d: d.update(suite_version=True),
        "not a submission (no integer suite_version)",
    ),
    "no rows": (lambda d: d.update(rows=[]), "sub.json: no rows"),
    "a seed as text": (set_row(seed="0"), "row 0 has seed '0', not an integer"),
    "half a lap counted": (set_row(laps_completed=0.5), "laps_completed 0.5 is not 0 to 1"),
    "a trajectory without its flags": (
        lambda d: first_row(d)["trajectory"].pop("outside"),
        "trajectory lacks the lists x_m, y_m, outside",
    ),
    "an intervention rate above 1": (
        lambda d: d["rows"][1].update(intervention_rate=1.5),
        "run lab/CenterLine/0/cbf: intervention_rate 1.5 is not a share in [0, 1]",
    ),
    "a filtered run without its interventions": (
        lambda d: d["rows"][1].update(intervention_rate=None),
        "run lab/CenterLine/0/cbf: intervention_rate None is not a share in [0, 1]",
    ),
    "more collisions caused than in all": (
        lambda d: traffic_row(d).update(collisions=0, at_fault_collisions=1),
        "at_fault_collisions 1 is more than the 0 collisions",
    ),
    "more overtakes than opponents": (
        lambda d: traffic_row(d).update(overtakes=2),
        "overtakes 2 is more than the 1 opponents",
    ),
    "a collision count as a fraction": (
        lambda d: traffic_row(d).update(collisions=0.5),
        "collisions is 0.5, not a whole number",
    ),
    "collisions on a lane run": (set_row(collisions=1), "collisions on a run without opponents"),
    "more collisions than control steps": (
        lambda d: traffic_row(d).update(collisions=10**400),
        "control steps",
    ),
    "a traffic run spelled as a lane run": (
        lambda d: traffic_row(d).update(filter="none/expert", opponents=None),
        "run lab/Overtake/0/none/expert is not a run of suite v2",
    ),
    "a traffic total missing": (lambda d: d.pop("traffic_score"), "missing field(s) traffic_score"),
    "a collision hidden": (lambda d: hide_a_collision(d), "score is "),
    "a replay of the wrong shape": (
        lambda d: d["replay"].update(files_sha256=["x.pt"]),
        "replay or versions has fields of the wrong type",
    ),
    "a replay without its sample count": (
        lambda d: d["replay"].pop("mc_samples"),
        "replay lacks agent, mc_samples, files_sha256, agent_sha256",
    ),
    "a file hash as a number": (
        lambda d: d["replay"].update(files_sha256={"agent.pt": 5}),
        "replay or versions has fields of the wrong type",
    ),
    "compiling named in words": (
        lambda d: d["replay"].update(compiled="false"),
        "replay or versions has fields of the wrong type",
    ),
    "faults written otherwise than a benchmark writes them": (
        lambda d: d["replay"].update(faults=["steering:offset=0.07"]),
        "replay faults ['steering:offset=0.07'] are not as written: "
        "['steering:severity=2,start=0,duration=inf,offset=0.07']",
    ),
    "a fault the suite does not know": (
        lambda d: d["replay"].update(faults=["smoke"]),
        "replay faults: unknown fault 'smoke' in 'smoke'",
    ),
    "faults as one string": (
        lambda d: d["replay"].update(faults="latency:steps=2"),
        "replay faults must be a list of one or more faults",
    ),
    "a replay of another agent": (
        lambda d: d["replay"].update(agent="expert"),
        "agent 'pure-pursuit' but replay agent 'expert'",
    ),
}


def test_an_honest_submission_passes_unchanged(honest: dict):
    assert check_submission(json.loads(json.dumps(honest)), SOURCE) == honest


#: Edits to the edge of what a run may hold, each still a consistent submission.
AT_THE_EDGE = {
    "every step corrected": lambda d: d["rows"][1].update(intervention_rate=1.0),
    "every collision caused": lambda d: traffic_row(d).update(collisions=1, at_fault_collisions=1),
    "every opponent passed": lambda d: traffic_row(d).update(overtakes=1),
    "a collision starting in every step": lambda d: traffic_row(d).update(
        collisions=round(traffic_row(d)["driven_s"] / CONTROL_DT_S),
        at_fault_collisions=round(traffic_row(d)["driven_s"] / CONTROL_DT_S),
    ),
    "a stall at the start, half a second long": lambda d: stand(first_row(d), 10),
    "a stall for the suite's whole time": lambda d: stand(first_row(d), 1200),
    "outside for the whole drive": lambda d: outside_at(stand(first_row(d), 10), 10, 0.5),
    "a jump at the top speed, rounded up a millimetre": lambda d: jump(
        stand(first_row(d), 10), TOP_SPEED_STEP_M + 0.001
    ),
    "a lap ending in the drive's last moment": lambda d: first_row(d).update(
        lap_time_s=first_row(d)["driven_s"]
    ),
    "a lap ending a whole step before the drive": lambda d: first_row(d).update(
        lap_time_s=first_row(d)["driven_s"] - CONTROL_DT_S
    ),
}


@pytest.mark.parametrize("case", AT_THE_EDGE)
def test_a_submission_at_the_edge_of_each_range_passes(honest: dict, case: str):
    edited = json.loads(json.dumps(honest))
    AT_THE_EDGE[case](edited)
    suite = load_suite()
    for row in edited["rows"]:
        row.update(scored(row, RunSpec.of_row(row), suite))
    edited.update(totals(edited["rows"], suite))
    assert check_submission(edited, SOURCE)["rows"] == edited["rows"]


@pytest.mark.parametrize("case", REFUSALS)
def test_a_doctored_submission_is_refused_naming_what_is_wrong(honest: dict, case: str):
    change, reason = REFUSALS[case]
    change(honest)
    with pytest.raises(SafeRaceError) as refused:
        check_submission(honest, SOURCE)
    message = str(refused.value)
    assert reason in message and "\n" not in message, message


def test_the_leaderboard_refuses_in_one_line_and_ranks_the_honest(
    honest_submission: Path, tmp_path: Path
):
    doctored = json.loads(honest_submission.read_text())
    halve_every_lap_time(doctored)
    path = tmp_path / "doctored.json"
    path.write_text(json.dumps(doctored))
    refused = run_cli("leaderboard", str(honest_submission), str(path))
    assert refused.returncode != 0
    row = doctored["rows"][0]
    assert refused.stderr.strip().splitlines() == [
        f"saferace leaderboard: error: {path}: run {FIRST}: the drive ({row['driven_s']:g} s) "
        f"went on after its last lap ({row['lap_time_s']:g} s)"
    ]
    accepted = run_cli("leaderboard", str(honest_submission))
    assert accepted.returncode == 0, accepted.stderr
    [line] = accepted.stdout.strip().splitlines()[2:]
    cells = [cell.strip() for cell in line.strip("|").split("|")]
    agent_hash = json.loads(honest_submission.read_text())["replay"]["agent_sha256"]
    assert cells[:5] == ["1", "pure-pursuit", "v2", agent_hash[:12], "no"]


def test_each_at_fault_collision_multiplies_the_run_score_by_the_suite_factor(honest: dict):
    suite = load_suite()
    row = traffic_row(honest)
    spec = RunSpec.of_row(row)
    clean = scored({**row, "at_fault_collisions": 0}, spec, suite)["score"]
    for count in (1, 2):
        penalised = scored({**row, "at_fault_collisions": count}, spec, suite)["score"]
        assert penalised == pytest.approx(clean * suite.traffic_set().collision_factor ** count)
    assert 0.0 < suite.traffic_set().collision_factor < 1.0


def as_version_1(submission: dict) -> dict:
    """``submission``'s lane runs as a submission of suite v1 would hold them: no traffic
    runs, fields or totals, every score from v1's references."""
    suite = load_suite(1)
    rows = []
    for row in submission["rows"]:
        if row.get("opponents") is not None:
            continue
        row = {k: v for k, v in row.items() if k not in ("opponents", *TRAFFIC_MEASUREMENTS)}
        row = {**row, "suite_version": 1}
        rows.append({**row, **scored(row, RunSpec.of_row(row), suite)})
    kept = {
        k: v for k, v in submission.items() if k not in totals(submission["rows"], load_suite())
    }
    return {**kept, "suite_version": 1, "rows": rows, **totals(rows, suite)}


def test_a_submission_of_the_old_version_is_scored_under_its_own(honest: dict):
    old = as_version_1(honest)
    assert "traffic_score" not in old and len(old["rows"]) == len(load_suite(1).runs())
    assert check_submission(json.loads(json.dumps(old)), SOURCE) == old
    current = check_submission(json.loads(json.dumps(honest)), SOURCE)
    better_old = {**old, "agent": "old", "score": 100.0}  # ranked only among its version
    ranked = leaderboard_rows([better_old, current])
    assert [(row[0], row[1], row[2]) for row in ranked] == [
        (1, "pure-pursuit", "v2"),
        (1, "old", "v1"),
    ]
    assert ranked[1][COLUMNS.index("traffic score")] is None
    mixed = json.loads(json.dumps(old))
    mixed["rows"].append(traffic_row(honest))  # a traffic run is no run of v1
    with pytest.raises(SafeRaceError, match="Overtake/0/none/expert is not a run of suite v1"):
        check_submission(mixed, SOURCE)


def test_the_page_shows_the_longest_standstill_and_old_rows_without_it_pass(honest: dict):
    """Each run records its longest standstill while the driver asked to move; the page
    shows the longest without and with the filter beside completion and the time outside,
    and it scores nothing: a submission whose rows predate it passes unchanged, shown
    without it."""
    rows = honest["rows"]
    assert all(row["longest_standstill_s"] >= 0.0 for row in rows)
    held = next(row for row in rows if row["filter"] != "none")
    held["longest_standstill_s"] = held["driven_s"]  # stood the whole drive, scored as before
    current = check_submission(json.loads(json.dumps(honest)), SOURCE)
    assert current == honest
    (line,) = leaderboard_rows([current])
    plain = [row["longest_standstill_s"] for row in rows if row["filter"] == "none"]
    assert line[COLUMNS.index("longest standstill [s]")] == max(plain)
    assert line[COLUMNS.index("longest standstill with filter [s]")] == held["driven_s"]
    assert line[COLUMNS.index("completion [%]")] == pytest.approx(100 * honest["completion"])
    old = json.loads(json.dumps(honest))
    for row in old["rows"]:
        del row["longest_standstill_s"]
    assert check_submission(json.loads(json.dumps(old)), SOURCE) == old
    (line,) = leaderboard_rows([old])
    assert line[COLUMNS.index("longest standstill [s]")] is None
    assert line[COLUMNS.index("longest standstill with filter [s]")] is None
    assert line[COLUMNS.index("score")] == current["score"]
    page = leaderboard_html([old], load_suite())
    assert "<th>longest standstill [s]</th>" in page


def test_the_page_escapes_every_string_of_a_submission(honest: dict):
    honest["agent"] = "<script>alert(1)</script>"
    honest["replay"]["agent_sha256"] = "<b>bold</b>" + "0" * 52
    page = leaderboard_html([honest], load_suite())
    assert "<script>alert(1)" not in page and "<b>bold" not in page
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in page and "&lt;b&gt;bold" in page


def test_verify_replays_an_honest_submission_and_marks_it_in_its_own_records(
    honest_submission: Path, tmp_path: Path
):
    path, records = tmp_path / "pp.json", tmp_path / "records"
    shutil.copy(honest_submission, path)
    result = verify_submission(path, runs=2, seed=3, progress=False, records=records)
    runs = len(load_suite().runs())
    assert result.passed and len(result.replayed) == 2 and result.total_runs == runs
    record = verification_record(path, records)
    assert record is not None and record["replayed"] == list(result.replayed)
    entry = {**check_submission(json.loads(path.read_text()), str(path)), "verification": record}
    assert leaderboard_rows([entry])[0][4] == f"2 of {runs}"
    shown = run_cli("leaderboard", str(path), "--verified-only", "--records", str(records))
    assert shown.returncode == 0 and f"2 of {runs}" in shown.stdout, shown.stderr
    elsewhere = run_cli("leaderboard", str(path), "--verified-only", "--records", str(tmp_path))
    assert elsewhere.returncode != 0  # a record is only worth the folder it is kept in
    path.write_text(json.dumps(json.loads(path.read_text()), indent=2))  # same rows, new bytes
    assert verification_record(path, records) is None
    listed = run_cli("leaderboard", str(path), "--verified-only", "--records", str(records))
    assert listed.returncode != 0 and "no submission has passed" in listed.stderr


def test_a_forged_or_broken_record_is_no_mark(honest_submission: Path, tmp_path: Path):
    from saferace.eval.runner import file_sha256
    from saferace.experiments.verify import record_path

    records = tmp_path / "records"
    record = record_path(file_sha256(honest_submission), records)
    record.parent.mkdir()
    for content in (b"\xff\xfe", b"[]", b'{"replayed": 3, "total_runs": 48}',
                    b'{"replayed": [1, 2, 3], "total_runs": 2}'):  # fmt: skip
        record.write_bytes(content)
        assert verification_record(honest_submission, records) is None


def test_verify_finds_the_edited_row_it_replays(honest_submission: Path, tmp_path: Path):
    edited = json.loads(honest_submission.read_text())
    keys = [row["key"] for row in edited["rows"]]
    [replayed] = choose_runs(keys, 1, seed=7)
    row = edited["rows"][keys.index(replayed)]
    row["mean_abs_deviation_m"] = 0.5 * row["mean_abs_deviation_m"]  # checked only by replay
    path = tmp_path / "edited.json"
    path.write_text(json.dumps(edited))
    check_submission(json.loads(path.read_text()), str(path))  # consistent on its face
    result = run_cli(
        "verify", str(path), "--runs", "1", "--seed", "7", "--records", str(tmp_path / "records")
    )
    assert result.returncode != 0
    assert (
        f"run {replayed}: mean_abs_deviation_m was {row['mean_abs_deviation_m']!r}"
        in (result.stderr.strip().splitlines()[-1])
    ), result.stderr
    # piped, the replay's progress is a line, the difference it found on it
    progress_line = result.stderr.splitlines()[0]
    assert progress_line.startswith(f"verify: {replayed} done (1/1 runs) in "), result.stderr
    assert ", score " in progress_line and "; mean_abs_deviation_m was" in progress_line


def hide_the_collisions(row: dict) -> str:
    row["at_fault_collisions"] = row["collisions"] = 0
    return "collisions was 0, replayed "


def shift_the_blame(row: dict) -> str:
    """The collisions stay counted, but none is the agent's any more."""
    was = row["at_fault_collisions"]
    row["at_fault_collisions"] = 0
    return f"at_fault_collisions was 0, replayed {was}"


def claim_an_overtake(row: dict) -> str:
    was = row["overtakes"]
    row["overtakes"] = was + 1
    return f"overtakes was {was + 1}, replayed {was}"


#: An edit of a traffic row that its scores are recomputed after, and the rows it applies to.
TRAFFIC_EDITS = {
    hide_the_collisions: lambda row: bool(row.get("at_fault_collisions")),
    shift_the_blame: lambda row: bool(row.get("at_fault_collisions")),
    claim_an_overtake: lambda row: row.get("overtakes") == 0,
}


@pytest.mark.parametrize("edit", list(TRAFFIC_EDITS), ids=lambda edit: edit.__name__)
def test_verify_finds_a_traffic_count_edited_with_its_scores_recomputed(
    honest_submission: Path, tmp_path: Path, edit
):
    edited = json.loads(honest_submission.read_text())
    keys = [row["key"] for row in edited["rows"]]
    rows = dict(zip(keys, edited["rows"], strict=True))
    seed = next(  # a draw that replays a run the edit applies to
        seed for seed in range(1000) if TRAFFIC_EDITS[edit](rows[choose_runs(keys, 1, seed)[0]])
    )
    [replayed] = choose_runs(keys, 1, seed)
    row = rows[replayed]
    expected = edit(row)
    suite = load_suite()
    row.update(scored(row, RunSpec.of_row(row), suite))
    edited.update(totals(edited["rows"], suite))
    path = tmp_path / "edited.json"
    path.write_text(json.dumps(edited))
    check_submission(json.loads(path.read_text()), str(path))  # consistent on its face
    result = verify_submission(path, runs=1, seed=seed, progress=False, records=tmp_path / "r")
    assert not result.passed
    assert result.mismatches[0].startswith(f"run {replayed}: {expected}"), result.mismatches


def test_verify_refuses_an_agent_file_swapped_after_the_runs(
    honest_submission: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    module = tmp_path / "my_agent.py"
    module.write_text(
        "from saferace.agents.pure_pursuit import PurePursuit\n\n\n"
        "def make(env):\n    return PurePursuit.for_env(env)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    data = json.loads(honest_submission.read_text())
    data["agent"], data["replay"] = "my_agent:make", replay_record("my_agent:make", 10)
    for row in data["rows"]:
        row["agent"], row["agent_sha256"] = data["agent"], data["replay"]["agent_sha256"]
    path = tmp_path / "mine.json"
    path.write_text(json.dumps(data))
    records = tmp_path / "records"
    assert verify_submission(path, runs=1, progress=False, records=records).passed
    assert verification_record(path, records) is not None  # pure pursuit's runs, replayed
    module.write_text(module.read_text() + "# a different agent now\n")
    with pytest.raises(SafeRaceError, match=r"my_agent.py changed since the runs \(sha256 "):
        verify_submission(path, runs=1, progress=False, records=records)
    assert verification_record(path, records) is None  # the earlier pass is withdrawn


def test_a_benchmark_of_an_agent_whose_file_is_missing_is_refused(tmp_path: Path):
    with pytest.raises(SafeRaceError, match=r"loads .*missing\.pt, which is not there"):
        replay_record(f"learned:{tmp_path / 'missing.pt'}", 10)


def test_an_agent_module_in_the_current_folder_is_found_as_the_console_script_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    import sys

    module = tmp_path / "folder_agent.py"
    module.write_text("def make(env):\n    return None\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", ".", str(tmp_path))])
    replay = replay_record("folder_agent:make", 10)  # the console script has no "" on its path
    assert replay["files_sha256"] == {str(module): file_sha256(module)}


def test_first_difference_holds_each_measurement_to_its_tolerance(honest: dict):
    from copy import deepcopy

    from saferace.experiments.verify import first_difference

    stored = next(row for row in honest["rows"] if row["laps_completed"])
    assert first_difference(stored, deepcopy(stored)) is None

    def replayed_with(edit) -> str | None:
        replayed = deepcopy(stored)
        edit(replayed)
        return first_difference(stored, replayed)

    def move_a_point(by_m: float):
        return lambda row: row["trajectory"]["x_m"].__setitem__(
            3, row["trajectory"]["x_m"][3] + by_m
        )

    assert replayed_with(move_a_point(0.001)) is None  # within a rounding step of 2 mm
    assert replayed_with(move_a_point(0.003)) == "trajectory differs by 0.003 m"
    shorter = replayed_with(lambda row: row["trajectory"]["x_m"].pop())
    assert shorter == "trajectory differs in length or outside flags"
    flags = stored["trajectory"]["outside"]
    flipped = replayed_with(
        lambda row: row["trajectory"].__setitem__("outside", [not f for f in flags])
    )
    assert flipped == "trajectory differs in length or outside flags"
    lap = stored["lap_time_s"]
    assert replayed_with(lambda row: row.__setitem__("lap_time_s", lap + 5e-7)) is None
    assert replayed_with(lambda row: row.__setitem__("lap_time_s", lap + 2e-6)) == (
        f"lap_time_s was {lap!r}, replayed {lap + 2e-6!r}"
    )
    assert replayed_with(lambda row: row.__setitem__("lap_time_s", None)) == (
        f"lap_time_s was {lap!r}, replayed None"
    )
    held = stored["longest_standstill_s"]
    assert replayed_with(lambda row: row.__setitem__("longest_standstill_s", held + 0.05)) == (
        f"longest_standstill_s was {held!r}, replayed {held + 0.05!r}"
    )
    older = {k: v for k, v in stored.items() if k != "longest_standstill_s"}
    assert first_difference(older, deepcopy(stored)) is None  # a row from before it verifies


def test_runs_are_drawn_all_in_order_or_a_seeded_sample_and_a_full_record_counts():
    keys = [f"run{i}" for i in range(10)]
    assert choose_runs(keys, None, seed=3) == keys == choose_runs(keys, 10, seed=3)
    drawn = choose_runs(keys, 4, seed=3)
    assert drawn == sorted(drawn, key=keys.index) and len(set(drawn)) == 4
    assert drawn == choose_runs(keys, 4, seed=3) != choose_runs(keys, 4, seed=4)
    with pytest.raises(SafeRaceError, match="at least 1"):
        choose_runs(keys, 0, seed=3)


def test_verify_keeps_its_records_in_a_new_folder_notes_other_versions_and_refuses_cleanly(
    honest_submission: Path, tmp_path: Path
):
    from saferace.eval.runner import file_sha256
    from saferace.experiments.verify import record_path

    data = json.loads(honest_submission.read_text())
    data["versions"]["numpy"] = "0.0"
    data["replay"]["vehicle_params_sha256"] = "0" * 64
    path = tmp_path / "other_machine.json"
    path.write_text(json.dumps(data))
    records = tmp_path / "new" / "records"  # made on the first pass, kept on the next
    for _ in range(2):
        result = verify_submission(path, runs=1, progress=False, records=records)
        assert result.passed and len(result.replayed) == 1
    notes = " / ".join(result.version_notes)
    assert "numpy 0.0 in the submission" in notes and "identified parameters differ" in notes
    full = json.loads(record_path(file_sha256(path), records).read_text())
    full["replayed"] = [row["key"] for row in data["rows"]]  # a pass of every run
    record_path(file_sha256(path), records).write_text(json.dumps(full))
    assert verification_record(path, records) == full
    replay = replay_record("pure-pursuit", 10) | {"agent": "gone_agent:make"}
    replay["files_sha256"] = {str(tmp_path / "gone_agent.py"): "0" * 64}
    data["agent"], data["replay"] = replay["agent"], replay
    for row in data["rows"]:
        row["agent"], row["agent_sha256"] = replay["agent"], replay["agent_sha256"]
    gone = tmp_path / "gone.json"
    gone.write_text(json.dumps(data))
    with pytest.raises(SafeRaceError, match=r"gone_agent\.py is not here"):
        verify_submission(gone, runs=1, progress=False, records=tmp_path / "empty")


def test_missing_runs_are_named_by_the_first_and_counted_after_it(honest: dict):
    messages = []
    for _ in range(2):
        honest["rows"].pop()
        with pytest.raises(SafeRaceError) as refused:
            check_submission(json.loads(json.dumps(honest)), SOURCE)
        messages.append(str(refused.value))
    missing = "sub.json: run eval_902/Overtake/0/{} of suite v2 is missing"
    assert messages == [
        missing.format("cbf/braking"),
        missing.format("none/braking") + " (and 1 more)",
    ]


def test_runs_replay_on_the_device_the_submissions_networks_ran_on():
    networks = {"files_sha256": {"agent.pt": "0" * 64}}
    assert replay_device({**networks, "device": "cuda:0"}) == "cuda:0"
    assert replay_device({**networks, "device": None}) == "cpu"
    assert replay_device(networks) == "cpu"  # made before submissions named their device
    assert replay_device({"files_sha256": {}, "device": "cuda:0"}) == "cpu"  # no network


def test_runs_replay_compiled_only_where_the_submissions_networks_ran_compiled(monkeypatch):
    monkeypatch.setenv(COMPILE_VARIABLE, "1")
    made = replay_record(f"learned:{Path(__file__)}", 10)  # any file stands in for weights
    assert made["compiled"] is True and replay_compiled(made)
    monkeypatch.setenv(COMPILE_VARIABLE, "0")
    assert replay_record(f"learned:{Path(__file__)}", 10)["compiled"] is False
    assert not replay_compiled({"files_sha256": {"agent.pt": "0" * 64}})  # made before
    assert not replay_compiled({**made, "compiled": False})
