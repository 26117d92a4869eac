"""Is a filter submission what the filter protocol would have measured? Checks before any
ranking, as :mod:`~saferace.experiments.submission_checks` makes them for drivers.

The board believes none of a submission's numbers that it can work out itself: every run's
liveness, fidelity, safety and score are recomputed from its measurements and the suite's
expert references (:func:`~saferace.experiments.filter_suite.scored_filter_run`), and the
entry's totals from its runs. A submission is refused, in one line naming the run and the
field, when it was made on a protocol version this SafeRace does not ship; its replay
record does not hash to its ``entry_sha256``; its runs are not exactly the protocol's
(every run once, no other; the circuits' too where it names their folder, which must hold
the files the protocol pins); a run was driven by another entry (its ``entry_sha256``); a
stored score or total differs from the recomputed one; or a measurement is impossible or
contradicts another (as for drivers: completion, time driven and outside, standstill,
laps, the trajectory; and the filter's clipped steps and error).

What passes is consistent, not proven: ``saferace verify`` drives the runs again.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import fields
from pathlib import Path

from saferace.errors import SafeRaceError
from saferace.experiments.filter_benchmark import PROTOCOL, FilterEntry
from saferace.experiments.filter_suite import (
    FilterRunSpec,
    FilterSuite,
    filter_totals,
    load_filter_suite,
    scored_filter_run,
)
from saferace.experiments.submission_checks import (
    CONTROL_DT_S,
    check_coverage,
    check_drive,
    check_intervention_rate,
    check_lap,
    check_same,
    check_trajectory,
    finite,
)

SUBMISSION_FIELDS = ("filter_suite_version", "circuits", "entry", "rows", "replay", "versions")
ROW_FIELDS = (
    "key", "entry_sha256", "filter_suite_version", "driver", "track", "condition", "opponents",
    "completion", "laps_completed", "lap_time_s", "driven_s", "time_outside_lane_s",
    "longest_standstill_s", "terminated", "intervention_rate", "clipped_steps",
    "filter_error", "at_fault_collisions", "collisions", "trajectory", "expert_lap_time_s",
    "lap_time_ratio", "liveness", "fidelity", "safe", "score", "mean_steer_correction_rad",
    "mean_accel_correction_mps2", "coverage",
)  # fmt: skip
#: A filtered run's measurements that are shares or sizes: a number >= 0 (a share <= 1).
FILTER_MEASUREMENTS = {
    "mean_steer_correction_rad": None,
    "mean_accel_correction_mps2": None,
    "coverage": 1.0,
}


def is_filter_submission(data: object) -> bool:
    """Whether ``data`` says it is a submission of the filter protocol."""
    return isinstance(data, dict) and data.get("protocol") == PROTOCOL


def is_filter_submission_file(path: str | Path) -> bool:
    """Whether the file ``path`` holds a submission of the filter protocol (False for one
    that cannot be read: the drivers' checks then say why)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return is_filter_submission(data)


def check_filter_submission(
    data: object, source: str, suite: FilterSuite | None = None, circuits: str | None = None
) -> dict:
    """``data`` with every score recomputed, if it is a consistent filter submission;
    otherwise a :class:`SafeRaceError` in one line naming the run and the field. The
    circuits of a submission with them are read from ``circuits``, else from the folder it
    names."""
    if not is_filter_submission(data):
        raise SafeRaceError(f"{source}: not a submission of the filter protocol")
    assert isinstance(data, dict)
    missing = [name for name in SUBMISSION_FIELDS if name not in data]
    if missing:
        raise SafeRaceError(f"{source}: missing field(s) {', '.join(missing)}")
    suite = suite or _own_suite(data["filter_suite_version"], source)
    if data["circuits"] is not None:
        if not isinstance(data["circuits"], str):
            raise SafeRaceError(f"{source}: circuits {data['circuits']!r} is not a folder")
        try:
            suite = suite.with_circuits(circuits or data["circuits"])
        except SafeRaceError as error:
            raise SafeRaceError(f"{source}: {error}") from None
    entry = _checked_entry(data, source)
    rows = data["rows"]
    if not isinstance(rows, list) or not rows or not all(isinstance(row, dict) for row in rows):
        raise SafeRaceError(f"{source}: rows must be a list of run objects")
    for index, row in enumerate(rows):
        absent = [name for name in ROW_FIELDS if name not in row]
        if absent:
            raise SafeRaceError(f"{source}: row {index} lacks {', '.join(absent)}")
    specs = [FilterRunSpec.of_row(row) for row in rows]
    check_coverage(specs, suite.runs(), source, f"filter protocol v{suite.version}")
    checked = []
    for row, spec in zip(rows, specs, strict=True):
        where = f"{source}: run {spec.key}"
        if row["key"] != spec.key:
            raise SafeRaceError(f"{where}: key is {row['key']!r}")
        if row["filter_suite_version"] != suite.version:
            raise SafeRaceError(f"{where}: of protocol v{row['filter_suite_version']}")
        if row["entry_sha256"] != data["replay"]["entry_sha256"]:
            raise SafeRaceError(f"{where}: driven by another entry (entry_sha256 differs)")
        _check_measurements(row, spec, suite, entry, where)
        recomputed = scored_filter_run(row, spec, suite)
        check_same(row, {k: v for k, v in recomputed.items() if k != "safe"}, where)
        stored_safe, safe = row["safe"], recomputed["safe"]
        if stored_safe != safe:
            raise SafeRaceError(f"{where}: safe is {stored_safe!r}, recomputed {safe}")
        checked.append({**row, **recomputed})
    totals = filter_totals(checked, suite)
    check_same(data, {name: value for name, value in totals.items() if name in data}, source)
    return {**data, **totals, "rows": checked}


def read_filter_submission(
    path: str, suite: FilterSuite | None = None, circuits: str | None = None
) -> dict:
    """The checked filter submission in ``path`` (its circuits read from ``circuits``, if
    given)."""
    try:
        with open(path) as file:
            data = json.load(file)
    except (OSError, json.JSONDecodeError) as error:
        raise SafeRaceError(f"{path}: cannot be read as JSON ({error})") from error
    return check_filter_submission(data, path, suite, circuits)


def _own_suite(version: object, source: str) -> FilterSuite:
    """The shipped filter protocol of the version a submission was made on."""
    if not isinstance(version, int) or isinstance(version, bool):
        raise SafeRaceError(f"{source}: filter_suite_version {version!r} is no version")
    try:
        return load_filter_suite(version)
    except SafeRaceError:
        raise SafeRaceError(
            f"{source}: made on filter protocol v{version}, which this SafeRace does not ship"
        ) from None


def _checked_entry(data: dict, source: str) -> FilterEntry:
    """The entry of the replay record, which must hash to its ``entry_sha256`` and be
    the one the submission names."""
    replay = data["replay"]
    names = {field.name for field in fields(FilterEntry)}
    if (
        not isinstance(replay, dict)
        or not isinstance(replay.get("entry"), dict)
        or set(replay["entry"]) != names
        or not isinstance(replay.get("files_sha256"), dict)
        or not isinstance(replay.get("entry_sha256"), str)
    ):
        raise SafeRaceError(f"{source}: replay lacks its entry, files_sha256 or entry_sha256")
    identity = json.dumps(
        {"entry": replay["entry"], "files": replay["files_sha256"]}, sort_keys=True
    )
    if hashlib.sha256(identity.encode()).hexdigest() != replay["entry_sha256"]:
        raise SafeRaceError(f"{source}: the replay record does not hash to its entry_sha256")
    entry = FilterEntry(**replay["entry"])
    if data["entry"] != entry.label:
        raise SafeRaceError(f"{source}: entry {data['entry']!r} but replay entry {entry.label!r}")
    return entry


def _whole(value: object, most: object) -> bool:
    """Whether ``value`` is a whole number (no bool) from 0 to ``most``."""
    return (
        isinstance(value, int) and not isinstance(value, bool)
        and isinstance(most, int) and 0 <= value <= most
    )  # fmt: skip


def _check_ending(row: dict, steps: int, suite: FilterSuite, filtered: bool, where: str) -> None:
    """A run ends for a reason: its laps done, the car out (terminated), the time limit, or
    its filter raised (then neither of the first two: that run ended at the error)."""
    error = row["filter_error"]
    if error is not None and not (filtered and isinstance(error, str) and error):
        raise SafeRaceError(f"{where}: filter_error {error!r} is no filter's error")
    done = row["laps_completed"] == suite.laps
    limit = steps == round(suite.max_seconds / CONTROL_DT_S)
    if not isinstance(row["terminated"], bool) or not isinstance(row["safe"], bool):
        raise SafeRaceError(f"{where}: terminated or safe is not true or false")
    if error is None and not (done or row["terminated"] or limit):
        raise SafeRaceError(
            f"{where}: the run ended after {steps} steps with no lap left, no termination and "
            "no filter error"
        )
    if error is not None and (done or row["terminated"]):
        raise SafeRaceError(f"{where}: filter_error on a run that ended otherwise")


def _check_measurements(
    row: dict, spec: FilterRunSpec, suite: FilterSuite, entry: FilterEntry, where: str
) -> None:
    """Raise unless the row's measurements are possible and agree with each other."""
    steps = check_drive(row, suite.max_seconds, where)
    check_lap(row, suite.laps, where)
    if not finite(row["longest_standstill_s"]):
        raise SafeRaceError(f"{where}: longest_standstill_s is {row['longest_standstill_s']!r}")
    filtered = entry.filter != "none"
    check_intervention_rate(row, filtered, where)
    for name, most in FILTER_MEASUREMENTS.items():
        value = row[name]
        fits = finite(value) and 0.0 <= value <= (most if most is not None else math.inf)
        if (value is not None or filtered) and not (filtered and fits):
            unfiltered = "" if filtered else " on a run without a filter"
            raise SafeRaceError(f"{where}: {name} is {value!r}{unfiltered}")
    clipped = row["clipped_steps"]
    if (clipped is not None or filtered) and not (filtered and _whole(clipped, steps)):
        raise SafeRaceError(f"{where}: clipped_steps {clipped!r} is not 0 to {steps} steps")
    _check_ending(row, steps, suite, filtered, where)
    collisions, at_fault = row["collisions"], row["at_fault_collisions"]
    if spec.opponents is None:
        if collisions is not None or at_fault is not None:
            raise SafeRaceError(f"{where}: collisions counted on a run without opponents")
    elif not (_whole(collisions, steps) and _whole(at_fault, collisions)):
        raise SafeRaceError(
            f"{where}: at_fault_collisions {at_fault!r} and collisions {collisions!r} are not "
            f"whole numbers with 0 <= at fault <= all <= {steps}"
        )
    check_trajectory(row, steps, where, suite.track_argument(spec.track), 0.0, suite.laps)
