"""``saferace verify``: drive a submission's runs again and compare every measurement.

The protocol is deterministic per seed, so anyone can check a submission by replaying it:
the files its agent loads must still have the sha256 recorded in the submission, and the
replayed runs (a seeded random sample, or all) must measure what the rows say, within
:data:`TOLERANCES`, on the device the submission was driven on (a CUDA run replays only on
CUDA, and cuDNN may not reproduce it). A pass is recorded in the verifier's own folder of
records (:func:`records_folder`), named by the submission file's sha256: a record shipped
beside a submission means nothing, and any edit of the file voids the mark. The
leaderboard shows the marks of the records in its folder: those its maintainer made.
"""

from __future__ import annotations

import json
import math
import os
import random
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from saferace.errors import SafeRaceError
from saferace.eval.parallel import run_jobs
from saferace.eval.runner import file_sha256, package_versions
from saferace.experiments.benchmark import (
    RunSpec,
    drive_run,
    load_suite,
    run_words,
)
from saferace.experiments.filter_benchmark import (
    FilterEntry,
    drive_filter_run,
    filter_replay_record,
    filter_run_words,
)
from saferace.experiments.filter_submission_checks import (
    is_filter_submission_file,
    read_filter_submission,
)
from saferace.experiments.filter_suite import FilterRunSpec, load_filter_suite
from saferace.experiments.replay_record import replay_faults, replay_record, vehicle_params_sha256
from saferace.experiments.submission_checks import read_submission
from saferace.learning.device import use_device
from saferace.names import COMPILE_VARIABLE, VERIFY_RUNS
from saferace.progress import Progress
from saferace.version import __version__

#: Measurement -> largest absolute difference accepted between the row and the replay
#: (None: must be equal). Floats get room for summation order across machines, and the
#: trajectory (stored to the millimetre) for one rounding step either way.
TOLERANCES: dict[str, float | None] = {
    "completion": 1e-6,
    "laps_completed": None,
    "lap_time_s": 1e-6,
    "driven_s": 1e-9,
    "mean_abs_deviation_m": 1e-6,
    "time_outside_lane_s": 1e-9,
    "longest_standstill_s": 1e-9,
    "terminated": None,
    "intervention_rate": 1e-9,
    "mean_steer_correction_rad": 1e-6,
    "mean_accel_correction_mps2": 1e-6,
    "collisions": None,
    "at_fault_collisions": None,
    "overtakes": None,
    "trajectory": 2e-3,
}
#: Measurements that rows written before they were recorded lack: compared only where the
#: submitted row has them, so that an older submission still verifies.
RECORDED_LATER = ("longest_standstill_s",)
#: A filter submission's runs also compare the filter's clipped steps, error and coverage.
FILTER_TOLERANCES: dict[str, float | None] = {
    **TOLERANCES,
    "clipped_steps": None,
    "filter_error": None,
    "coverage": 1e-9,
}


@dataclass(frozen=True)
class Verification:
    """The outcome of one ``verify``: the runs replayed, and how each differs (if at all)."""

    submission_sha256: str
    replayed: tuple[str, ...]
    total_runs: int
    mismatches: tuple[str, ...]
    version_notes: tuple[str, ...]

    @property
    def passed(self) -> bool:
        return not self.mismatches


#: Where ``verify`` keeps its records, unless told otherwise.
RECORDS_VARIABLE = "SAFERACE_VERIFIED"


def records_folder(folder: str | Path | None = None) -> Path:
    """The folder of verification records: ``folder``, else :data:`RECORDS_VARIABLE`, else
    ``~/.cache/saferace/verified``."""
    chosen = folder or os.environ.get(RECORDS_VARIABLE) or "~/.cache/saferace/verified"
    return Path(chosen).expanduser()


def record_path(submission_sha256: str, folder: str | Path | None = None) -> Path:
    """The record of the submission whose file has ``submission_sha256``."""
    return records_folder(folder) / f"{submission_sha256}.json"


def verification_record(submission: str | Path, folder: str | Path | None = None) -> dict | None:
    """The record of a verification of ``submission`` in its current form, if ``folder``
    (see :func:`records_folder`) holds a sound one."""
    try:
        data = json.loads(record_path(file_sha256(submission), folder).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(data, dict):
        return None
    replayed, total = data.get("replayed"), data.get("total_runs")
    if not isinstance(replayed, list) or not isinstance(total, int) or len(replayed) > total:
        return None
    return data


def check_agent_files(replay: dict, source: str) -> None:
    """Raise unless every file the agent loads has the sha256 recorded at submission."""
    _check_files(replay["files_sha256"], source)
    now = replay_record(replay["agent"], replay["mc_samples"], replay_faults(replay))
    if now["agent_sha256"] != replay["agent_sha256"]:
        raise SafeRaceError(
            f"{source}: the replay record does not hash to its agent_sha256 "
            f"({replay['agent_sha256'][:12]} recorded, {now['agent_sha256'][:12]} computed)"
        )


def _check_files(files_sha256: dict[str, str], source: str) -> None:
    """Raise unless every file has its recorded sha256 here."""
    for path, digest in files_sha256.items():
        if not Path(path).is_file():
            raise SafeRaceError(
                f"{source}: the submission's file {path} is not here: run verify from the "
                "folder the benchmark ran in"
            )
        if file_sha256(path) != digest:
            raise SafeRaceError(
                f"{source}: the submission's file {path} changed since the runs (sha256 "
                f"{digest[:12]} recorded, {file_sha256(path)[:12]} now)"
            )


def first_difference(
    stored: dict, replayed: dict, tolerances: dict[str, float | None] = TOLERANCES
) -> str | None:
    """The first measurement in which ``replayed`` differs from ``stored``, described."""
    for name, tolerance in tolerances.items():
        if name == "trajectory":
            difference = _trajectory_difference(stored[name], replayed[name])
            if difference is None:
                return "trajectory differs in length or outside flags"
            if difference > (tolerance or 0.0):
                return f"trajectory differs by {difference:.3f} m"
            continue
        if name in RECORDED_LATER and name not in stored:
            continue
        was, now = stored.get(name), replayed.get(name)
        if was is None or now is None or tolerance is None:
            if was != now:
                return f"{name} was {was!r}, replayed {now!r}"
        elif not math.isclose(was, now, rel_tol=0.0, abs_tol=tolerance):
            return f"{name} was {was!r}, replayed {now!r}"
    return None


def _trajectory_difference(was: dict, now: dict) -> float | None:
    """Largest distance between matching points, or None if the points or flags differ."""
    if len(was["x_m"]) != len(now["x_m"]) or was["outside"] != now["outside"]:
        return None
    return max(
        (
            math.hypot(x0 - x1, y0 - y1)
            for x0, y0, x1, y1 in zip(was["x_m"], was["y_m"], now["x_m"], now["y_m"], strict=True)
        ),
        default=0.0,
    )


def choose_runs(keys: list[str], count: int | None, seed: int) -> list[str]:
    """``count`` of ``keys`` drawn with ``seed`` (all of them, in order, for None)."""
    if count is None or count >= len(keys):
        return list(keys)
    if count < 1:
        raise SafeRaceError(f"--runs must be at least 1, got {count}")
    return sorted(random.Random(seed).sample(keys, count), key=keys.index)


def verify_submission(
    path: str | Path,
    runs: int | None = VERIFY_RUNS,
    workers: int = 1,
    seed: int = 0,
    progress: bool = True,
    records: str | Path | None = None,
    circuits: str | None = None,
) -> Verification:
    """Replay ``runs`` of the submission in ``path`` (None: all) and compare. A pass writes
    its record into ``records`` (see :func:`records_folder`; a filter submission's circuits
    are read from ``circuits``, if given); a refusal, a mismatch or a
    failure removes an earlier one."""
    path = Path(path)
    sha256 = file_sha256(path)  # of the bytes checked: a file changed meanwhile gets no mark
    record = record_path(sha256, records)
    try:
        result = _replay(path, sha256, runs, workers, seed, progress, circuits)
    except Exception:
        record.unlink(missing_ok=True)
        raise
    if not result.passed:
        record.unlink(missing_ok=True)
        return result
    record.parent.mkdir(parents=True, exist_ok=True)
    entry = {
        "submission_sha256": sha256,
        "submission": str(path.resolve()),
        "replayed": list(result.replayed),
        "total_runs": result.total_runs,
        "seed": seed,
        "saferace": __version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    record.write_text(json.dumps(entry, indent=1) + "\n")
    return result


def replay_device(replay: dict) -> str:
    """The device a submission's runs replay on: the one its networks ran on; the CPU if
    it names none, or has no network files to run."""
    if not replay["files_sha256"]:
        return "cpu"
    return replay.get("device") or "cpu"


def replay_compiled(replay: dict) -> bool:
    """Whether a submission's networks replay compiled for the CPU: as they ran (compiled
    and eager results differ in the last digits, which a lap amplifies); eagerly for a
    submission made before networks were compiled."""
    return bool(replay.get("compiled"))


@dataclass(frozen=True)
class Replayable:
    """A checked submission as ``verify`` replays it: its rows by run key, each run's job
    for ``drive``, how a replayed row is said, and what is compared within what."""

    data: dict
    rows: dict[str, dict]
    jobs: dict[str, tuple]
    drive: Callable[..., dict]
    words: Callable[[dict], str]
    tolerances: dict[str, float | None]


def replayable(path: Path, circuits: str | None = None) -> Replayable:
    """The submission in ``path``, checked, as a driver's or a filter's, its files checked
    to be those it was driven with (a filter submission's circuits read from ``circuits``,
    if given)."""
    if is_filter_submission_file(path):
        data = read_filter_submission(str(path), circuits=circuits)
        check_entry_files(data["replay"], str(path))
        filter_suite = load_filter_suite(data["filter_suite_version"])
        if data["circuits"] is not None:  # checked: holds the circuits the protocol pins
            filter_suite = filter_suite.with_circuits(circuits or data["circuits"])
        entry = FilterEntry(**data["replay"]["entry"])
        rows = {row["key"]: row for row in data["rows"]}
        jobs: dict[str, tuple] = {
            key: (entry, FilterRunSpec.of_row(row), filter_suite) for key, row in rows.items()
        }
        return Replayable(data, rows, jobs, drive_filter_run, filter_run_words, FILTER_TOLERANCES)
    data = read_submission(path)
    replay = data["replay"]
    check_agent_files(replay, str(path))
    suite = load_suite(data["suite_version"])  # checked: a version this SafeRace ships
    rows = {RunSpec.of_row(row).key: row for row in data["rows"]}
    faults = replay_faults(replay)
    jobs = {
        key: (replay["agent"], RunSpec.of_row(row), suite, replay["mc_samples"], faults)
        for key, row in rows.items()
    }
    return Replayable(data, rows, jobs, drive_run, run_words, TOLERANCES)


def check_entry_files(replay: dict, source: str) -> None:
    """Raise unless every file a filter entry loads has the sha256 recorded at submission."""
    _check_files(replay["files_sha256"], source)
    now = filter_replay_record(FilterEntry(**replay["entry"]))
    if now["entry_sha256"] != replay["entry_sha256"]:
        raise SafeRaceError(
            f"{source}: the entry's files are not those it was driven with (entry hash "
            f"{replay['entry_sha256'][:12]} recorded, {now['entry_sha256'][:12]} now)"
        )


def _replay(
    path: Path,
    sha256: str,
    runs: int | None,
    workers: int,
    seed: int,
    progress: bool,
    circuits: str | None,
) -> Verification:
    submission = replayable(path, circuits)
    data, rows = submission.data, submission.rows
    replay = data["replay"]
    use_device(replay_device(replay))
    os.environ[COMPILE_VARIABLE] = "1" if replay_compiled(replay) else "0"  # and its workers
    chosen = choose_runs(list(rows), runs, seed)
    installed = {"saferace": __version__, **package_versions()}
    notes = tuple(
        f"{name} {was} in the submission, {installed.get(name)} here"
        for name, was in data["versions"].items()
        if installed.get(name) != was
    )
    if replay.get("vehicle_params_sha256") not in (None, vehicle_params_sha256()):
        notes += ("the car's identified parameters differ from the submission's: the "
                  "expert's and the filter's runs will not replay",)  # fmt: skip
    replayed: dict[str, dict] = {}
    tolerances = submission.tolerances

    def replayed_words(key: str) -> str:
        row = replayed.get(key)
        if row is None:
            return "failed"
        difference = first_difference(rows[key], row, tolerances)
        return f"{submission.words(row)}; {'as submitted' if difference is None else difference}"

    with Progress(len(chosen), "verify", "run", enabled=progress) as bar:
        run_jobs(
            submission.drive,
            [submission.jobs[key] for key in chosen],
            lambda job, row: replayed.__setitem__(job[1].key, row),
            workers=workers,
            advance=lambda job: bar.done(job[1].key, replayed_words(job[1].key)),
            describe=lambda job: job[1].key,
        )
    mismatches = tuple(
        f"run {key}: {difference}"
        for key in chosen
        if (difference := first_difference(rows[key], replayed[key], tolerances)) is not None
    )
    return Verification(sha256, tuple(chosen), len(rows), mismatches, notes)
