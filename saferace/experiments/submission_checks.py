"""Is a benchmark submission what the suite would have measured? Checks before any ranking.

A submission is a JSON file anyone can edit, so the leaderboard believes none of its
numbers it can work out itself: every run's ratios and score are recomputed from the run's
measurements and the suite's stored expert references (:func:`~saferace.experiments.
benchmark.scored`), and the agent's scores from its runs (:func:`~saferace.experiments.
benchmark.totals`). A submission is refused, in one line naming the run and the field, when

- it was made on a suite version this SafeRace does not ship (one it ships checks and
  scores it under its own version);
- its runs are not exactly the suite's: every (track, task, start, filter, opponents) once,
  no other;
- a stored score or ratio differs from the recomputed one beyond rounding;
- a measurement is physically impossible or contradicts another: completion outside
  [0, 1]; an episode longer than the suite allows or not a whole number of control steps;
  more time outside the lane than driven, or a different time than the trajectory's
  outside flags allow; a longest standstill (where the row has one) below zero or longer
  than the drive; a finished lap without full completion or longer than the drive;
  a trajectory with the wrong number of points, faster than the car's top speed between
  two points, not starting at the run's start, or much shorter than the distance the
  completion claims; a filtered run without its intervention rate; a traffic run's
  collision counts not whole numbers, more at fault than in all, or more overtakes than
  opponents.

What passes is consistent, not proven: ``saferace verify`` drives the runs again.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from functools import cache
from pathlib import Path

import numpy as np

from saferace.envs.drivetrain import DrivetrainParams
from saferace.envs.racing_env import DEFAULT_CONTROL_HZ
from saferace.errors import SafeRaceError
from saferace.experiments.benchmark import (
    SUITE_VERSION,
    TRAFFIC_MEASUREMENTS,
    TRAFFIC_TOTALS,
    TRAJECTORY_POINTS,
    RunSpec,
    Suite,
    load_suite,
    scored,
    totals,
)
from saferace.faults.spec import FaultError, canonical_faults
from saferace.track import Track

SUBMISSION_FIELDS = (
    "suite_version",
    "agent",
    "score",
    "score_with_filter",
    "intervention_rate",
    "completion",
    "time_outside_lane_s",
    "rows",
    "replay",
    "versions",
)
ROW_FIELDS = (
    "track",
    "task",
    "seed",
    "filter",
    "completion",
    "laps_completed",
    "lap_time_s",
    "driven_s",
    "time_outside_lane_s",
    "intervention_rate",
    "trajectory",
    "expert_lap_time_s",
    "lap_time_ratio",
    "speed_ratio",
    "score",
)
#: Measurements that are a number or None (no lap, no filter).
OPTIONAL_NUMBERS = (
    "lap_time_s",
    "mean_abs_deviation_m",
    "mean_steer_correction_rad",
    "mean_accel_correction_mps2",
)
RELATIVE_ROUNDING = 1e-6  # stored scores may differ from recomputed ones by this much
CONTROL_DT_S = 1.0 / DEFAULT_CONTROL_HZ
TRAJECTORY_DECIMALS_M = 1e-3  # trajectories are stored to the millimetre
START_TOLERANCE_M = 0.5  # the first point is within the lane's half width and this of its start
#: At least this much of the distance its completion claims is driven: a racing line cuts
#: corners (0.93), a car that turns round drives more (no upper bound).
MIN_PATH_TO_PROGRESS = 0.6
MIN_PROGRESS_FOR_PATH_CHECK_M = 2.0


def check_submission(data: object, source: str, suite: Suite | None = None) -> dict:
    """``data`` with every score recomputed, if it is a consistent submission of ``suite``
    (default: the shipped suite of the version it was made on); otherwise a
    :class:`SafeRaceError` in one line."""
    suite = suite or _own_suite(data, source)
    _check_structure(data, source, suite)
    assert isinstance(data, dict)
    _check_replay(data, source)
    rows = data["rows"]
    specs = [_run_spec(row, index, source) for index, row in enumerate(rows)]
    _check_coverage(specs, source, suite)
    checked = []
    for row, spec in zip(rows, specs, strict=True):
        where = f"{source}: run {spec.key}"
        if row["suite_version"] != suite.version:
            raise SafeRaceError(f"{where}: of suite v{row['suite_version']}, not v{suite.version}")
        if row.get("agent_sha256") != data["replay"]["agent_sha256"]:
            raise SafeRaceError(f"{where}: driven by another agent (agent_sha256 differs)")
        _check_measurements(row, spec, suite, where)
        recomputed = scored(row, spec, suite)
        check_same(row, recomputed, where)
        checked.append({**row, **recomputed})
    recomputed_totals = totals(checked, suite)
    check_same(data, recomputed_totals, source)
    return {**data, **recomputed_totals, "rows": checked}


def read_submission(path: str | Path, suite: Suite | None = None) -> dict:
    """The checked submission in ``path`` (see :func:`check_submission`)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise SafeRaceError(f"{path}: cannot be read as JSON ({error})") from error
    return check_submission(data, str(path), suite)


def _own_suite(data: object, source: str) -> Suite:
    """The shipped suite of the version ``data`` was made on."""
    version = data.get("suite_version") if isinstance(data, dict) else None
    if not isinstance(version, int) or isinstance(version, bool):
        raise SafeRaceError(f"{source}: not a submission (no integer suite_version)")
    try:
        return load_suite(version)
    except SafeRaceError:
        raise SafeRaceError(
            f"{source}: made on suite v{version}, which this SafeRace does not ship (it "
            f"scores v1 to v{SUITE_VERSION}): run saferace benchmark again"
        ) from None


def _check_structure(data: object, source: str, suite: Suite) -> None:
    if not isinstance(data, dict):
        raise SafeRaceError(f"{source}: not a submission (a JSON object is expected)")
    required = SUBMISSION_FIELDS + (TRAFFIC_TOTALS if suite.traffic is not None else ())
    missing = [name for name in required if name not in data]
    if missing:
        raise SafeRaceError(f"{source}: missing field(s) {', '.join(missing)}")
    if data["suite_version"] != suite.version:
        raise SafeRaceError(
            f"{source}: made on suite v{data['suite_version']}, "
            f"this leaderboard is v{suite.version}"
        )
    for name in ("score", "score_with_filter", "intervention_rate", "completion"):
        value = data[name]
        if value is not None and not finite(value):
            raise SafeRaceError(f"{source}: {name} is {value!r}, not a finite number")
    if not isinstance(data["rows"], list) or not data["rows"]:
        raise SafeRaceError(f"{source}: no rows")
    for index, row in enumerate(data["rows"]):
        if not isinstance(row, dict):
            raise SafeRaceError(f"{source}: row {index} is not an object")
        absent = [name for name in ("suite_version", *ROW_FIELDS) if name not in row]
        if absent:
            raise SafeRaceError(f"{source}: row {index} lacks {', '.join(absent)}")


def _check_replay(data: dict, source: str) -> None:
    replay = data["replay"]
    fields = ("agent", "mc_samples", "files_sha256", "agent_sha256")
    if not isinstance(replay, dict) or any(name not in replay for name in fields):
        raise SafeRaceError(f"{source}: replay lacks {', '.join(fields)}")
    files = replay["files_sha256"]
    if (
        not isinstance(replay["agent"], str)
        or not isinstance(replay["mc_samples"], int)
        or not isinstance(replay["agent_sha256"], str)
        or not isinstance(files, dict)
        or not all(isinstance(k, str) and isinstance(v, str) for k, v in files.items())
        or not isinstance(replay.get("device") or "", str)
        or not isinstance(replay.get("compiled", False), bool | None)
        or not isinstance(data["versions"], dict)
    ):
        raise SafeRaceError(f"{source}: replay or versions has fields of the wrong type")
    if replay["agent"] != data["agent"]:
        raise SafeRaceError(
            f"{source}: agent {data['agent']!r} but replay agent {replay['agent']!r}"
        )
    _check_faults(replay, source)


def _check_faults(replay: dict, source: str) -> None:
    """The faults a submission drove under: a list of fault strings, written one way."""
    faults = replay.get("faults", [])
    if not isinstance(faults, list) or (not faults and "faults" in replay):
        raise SafeRaceError(f"{source}: replay faults must be a list of one or more faults")
    try:
        written = list(canonical_faults(faults))
    except FaultError as error:
        raise SafeRaceError(f"{source}: replay faults: {error}") from None
    if written != faults:
        raise SafeRaceError(f"{source}: replay faults {faults} are not as written: {written}")


def _run_spec(row: dict, index: int, source: str) -> RunSpec:
    if not isinstance(row["seed"], int) or isinstance(row["seed"], bool):
        raise SafeRaceError(f"{source}: row {index} has seed {row['seed']!r}, not an integer")
    return RunSpec.of_row(row)


def _check_coverage(specs: list[RunSpec], source: str, suite: Suite) -> None:
    """Every run of the suite once, no other: runs compared field by field (a filter named
    ``none/expert`` spells a traffic run's key, and is still no run of the suite)."""
    check_coverage(specs, suite.runs(), source, f"suite v{suite.version}")


def check_coverage(specs: list, wanted: list, source: str, protocol: str) -> None:
    """Raise unless ``specs`` (runs with a ``key``) are ``wanted``, each once, no other;
    ``protocol`` names what they are runs of."""
    counts = Counter(specs)
    repeated = [spec for spec, count in counts.items() if count > 1]
    if repeated:
        raise SafeRaceError(f"{source}: run {repeated[0].key} appears {counts[repeated[0]]} times")
    extra = [spec for spec in counts if spec not in wanted]
    if extra:
        raise SafeRaceError(f"{source}: run {extra[0].key} is not a run of {protocol}")
    absent = [spec for spec in wanted if spec not in counts]
    if absent:
        more = f" (and {len(absent) - 1} more)" if len(absent) > 1 else ""
        raise SafeRaceError(f"{source}: run {absent[0].key} of {protocol} is missing{more}")


def _check_measurements(row: dict, spec: RunSpec, suite: Suite, where: str) -> None:
    """Raise unless the row's measurements are possible and agree with each other."""
    steps = check_drive(row, suite.max_seconds_of(spec), where)
    check_lap(row, suite.laps_of(spec), where)
    _check_traffic(row, spec, suite, steps, where)
    check_intervention_rate(row, spec.filter != "none", where)
    check_trajectory(
        row, steps, where, suite.track_argument(spec.track),
        suite.start_fraction(spec), suite.laps_of(spec),
    )  # fmt: skip


def check_drive(row: dict, max_seconds: float, where: str) -> int:
    """The control steps a row's drive took, unless its completion, time driven, time
    outside or longest standstill is impossible or contradicts another."""
    for name in ("completion", "driven_s", "time_outside_lane_s"):
        if not finite(row[name]):
            raise SafeRaceError(f"{where}: {name} is {row[name]!r}, not a finite number")
    for name in OPTIONAL_NUMBERS:
        if row.get(name) is not None and not finite(row[name]):
            raise SafeRaceError(f"{where}: {name} is {row[name]!r}, not a finite number")
    if not isinstance(row.get("terminated"), bool):
        raise SafeRaceError(f"{where}: terminated is {row.get('terminated')!r}, not true or false")
    completion, driven_s, outside_s = row["completion"], row["driven_s"], row["time_outside_lane_s"]
    if not 0.0 <= completion <= 1.0:
        raise SafeRaceError(f"{where}: completion {completion} is outside [0, 1]")
    steps = driven_s / CONTROL_DT_S
    within = 0.0 < driven_s <= max_seconds + 1e-9
    if not within or not math.isclose(steps, round(steps), abs_tol=1e-6):
        raise SafeRaceError(
            f"{where}: driven_s {driven_s} is not 1 to {max_seconds:g} s of whole "
            f"{CONTROL_DT_S:g} s control steps"
        )
    if not 0.0 <= outside_s <= driven_s:
        raise SafeRaceError(
            f"{where}: time_outside_lane_s {outside_s} is not within the {driven_s:g} s driven"
        )
    standstill_s = row.get("longest_standstill_s")  # None: a row from before it was recorded
    if standstill_s is not None and not (finite(standstill_s) and 0.0 <= standstill_s <= driven_s):
        raise SafeRaceError(
            f"{where}: longest_standstill_s {standstill_s!r} is not within the {driven_s:g} s "
            "driven"
        )
    return round(steps)


def check_intervention_rate(row: dict, filtered: bool, where: str) -> None:
    """A run behind a filter has a share of interventions, one without none."""
    rate = row["intervention_rate"]
    if not filtered and rate is not None:
        raise SafeRaceError(f"{where}: intervention_rate {rate} on a run without a filter")
    if filtered and not (finite(rate) and 0.0 <= rate <= 1.0):
        raise SafeRaceError(f"{where}: intervention_rate {rate!r} is not a share in [0, 1]")


def _check_traffic(row: dict, spec: RunSpec, suite: Suite, steps: int, where: str) -> None:
    """A traffic run's counts are whole and possible (a collision starts in a control step
    at most once); a lane run has none."""
    if spec.opponents is None:
        counted = [name for name in TRAFFIC_MEASUREMENTS if row.get(name) is not None]
        if counted:
            raise SafeRaceError(f"{where}: {counted[0]} on a run without opponents")
        return
    counts: dict[str, int] = {}
    for name in TRAFFIC_MEASUREMENTS:
        value = row.get(name)
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise SafeRaceError(f"{where}: {name} is {value!r}, not a whole number")
        counts[name] = value
    if counts["collisions"] > steps:
        raise SafeRaceError(
            f"{where}: collisions {counts['collisions']} is more than the {steps} control steps"
        )
    if counts["at_fault_collisions"] > counts["collisions"]:
        raise SafeRaceError(
            f"{where}: at_fault_collisions {counts['at_fault_collisions']} is more than the "
            f"{counts['collisions']} collisions"
        )
    opponents = len(suite.traffic_set().opponents[spec.opponents])
    if counts["overtakes"] > opponents:
        raise SafeRaceError(
            f"{where}: overtakes {counts['overtakes']} is more than the {opponents} opponents"
        )


def check_lap(row: dict, suite_laps: int, where: str) -> None:
    laps, lap_time_s = row["laps_completed"], row["lap_time_s"]
    if not isinstance(laps, int) or not 0 <= laps <= suite_laps:
        raise SafeRaceError(f"{where}: laps_completed {laps!r} is not 0 to {suite_laps}")
    if laps == 0:
        if lap_time_s is not None:
            raise SafeRaceError(f"{where}: lap_time_s {lap_time_s} without a completed lap")
        return
    if not finite(lap_time_s):
        raise SafeRaceError(f"{where}: lap_time_s is {lap_time_s!r}, not a finite number")
    if laps == suite_laps and row["completion"] != 1.0:
        raise SafeRaceError(f"{where}: every lap completed but completion is {row['completion']}")
    driven_s = row["driven_s"]
    if not laps * lap_time_s <= driven_s + 1e-9:
        raise SafeRaceError(f"{where}: lap_time_s {lap_time_s} is longer than the drive")
    if laps == suite_laps and driven_s - laps * lap_time_s > CONTROL_DT_S + 1e-9:
        raise SafeRaceError(
            f"{where}: the drive ({driven_s:g} s) went on after its last lap ({lap_time_s:g} s)"
        )


def check_trajectory(
    row: dict, steps: int, where: str, track_argument: str, start_fraction: float, laps: int
) -> None:
    """Raise unless the row's trajectory has the points ``steps`` steps give, moves no
    faster than the car, agrees with the time outside, starts at ``start_fraction`` of the
    lap of ``track_argument`` and is about as long as the completion of ``laps`` claims."""
    trajectory = row["trajectory"]
    names = ("x_m", "y_m", "outside")
    if not isinstance(trajectory, dict) or any(
        not isinstance(trajectory.get(name), list) for name in names
    ):
        raise SafeRaceError(f"{where}: trajectory lacks the lists {', '.join(names)}")
    stride = max(1, steps // TRAJECTORY_POINTS)
    expected = math.ceil(steps / stride)
    lengths = {len(trajectory[name]) for name in names}
    if lengths != {expected}:
        raise SafeRaceError(
            f"{where}: trajectory has {sorted(lengths)} points, {expected} for {steps} steps"
        )
    coordinates = [*trajectory["x_m"], *trajectory["y_m"]]
    if not all(finite(value) for value in coordinates) or not all(
        isinstance(flag, bool) for flag in trajectory["outside"]
    ):
        raise SafeRaceError(f"{where}: trajectory points are not finite numbers, or flags not")
    xy = np.column_stack([trajectory["x_m"], trajectory["y_m"]]).astype(float)
    stride_s = stride * CONTROL_DT_S
    top_speed = DrivetrainParams().top_speed_mps
    segments = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    fastest = float(segments.max(initial=0.0))
    if fastest > top_speed * stride_s + 2.0 * TRAJECTORY_DECIMALS_M:
        raise SafeRaceError(
            f"{where}: the trajectory moves {fastest / stride_s:.2f} m/s between two points, "
            f"faster than the car's top speed ({top_speed:g} m/s)"
        )
    flagged = sum(bool(flag) for flag in trajectory["outside"])
    outside_s = row["time_outside_lane_s"]
    if not flagged * CONTROL_DT_S - 1e-9 <= outside_s <= flagged * stride_s + 1e-9:
        raise SafeRaceError(
            f"{where}: time_outside_lane_s {outside_s} disagrees with the trajectory, outside "
            f"at {flagged} of its points ({flagged * CONTROL_DT_S:g}-{flagged * stride_s:g} s)"
        )
    track = _load_track(track_argument)
    start_m = start_fraction * track.length_m
    start = track.centerline.position(np.array([start_m]))[0]
    half_width = max(track.widths(start_m))
    if np.linalg.norm(xy[0] - start) > half_width + START_TOLERANCE_M:
        raise SafeRaceError(f"{where}: the trajectory does not start at the run's start")
    progress_m = row["completion"] * laps * track.length_m
    if progress_m >= MIN_PROGRESS_FOR_PATH_CHECK_M:
        ratio = float(segments.sum()) / progress_m
        if ratio < MIN_PATH_TO_PROGRESS:
            raise SafeRaceError(
                f"{where}: the trajectory is {segments.sum():.1f} m long, {ratio:.2f} times the "
                f"{progress_m:.1f} m that completion {row['completion']:.3f} claims"
            )


def check_same(stored: dict, recomputed: dict, where: str) -> None:
    for name, value in recomputed.items():
        carried = stored[name]
        same = (
            carried is None
            if value is None
            else finite(carried)
            and math.isclose(carried, value, rel_tol=RELATIVE_ROUNDING, abs_tol=1e-9)
        )
        if not same:
            raise SafeRaceError(f"{where}: {name} is {carried!r}, recomputed {value!r}")


def finite(value: object) -> bool:
    if not isinstance(value, int | float) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an int too large for a float
        return False


_load_track = cache(Track.load)  # the suite's few tracks, loaded once per process
