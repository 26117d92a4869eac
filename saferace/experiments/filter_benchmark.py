"""``saferace benchmark --filter``: an entry (a filter and its perception) driven through the
filter protocol (:mod:`saferace.experiments.filter_suite`), written as a submission.

Runs are journaled in ``OUT.runs.jsonl`` as they end, so that a run interrupted goes on
where it stopped; over worker processes or as Ray tasks. The submission holds every run's
row, the entry's totals, and its replay record: the entry, the sha256 of every file it
loads (a filter's or perception's module, a checkpoint, the generic model) and one hash of
them all (``entry_sha256``), the device its networks ran on and the car's parameters'
sha256, what ``saferace verify`` needs to drive the runs again.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

from saferace.envs.unwrap import racing_env
from saferace.errors import SafeRaceError
from saferace.eval.agents import agent_files, make_agent
from saferace.eval.filter_config import STATE_SOURCE_FACTORIES, users_filter, users_perception
from saferace.eval.filters import FilterConfig
from saferace.eval.runner import (
    file_sha256,
    make_task_env,
    max_steps_for,
    read_jsonl,
    run_episode,
    standstill_words,
)
from saferace.experiments.benchmark import episode_measurements, provenance, write_submission
from saferace.experiments.filter_suite import (
    Condition,
    FilterRunSpec,
    FilterSuite,
    filter_totals,
    load_filter_suite,
    scored_filter_run,
)
from saferace.experiments.journal import journaled_runs
from saferace.experiments.replay_record import network_settings, vehicle_params_sha256
from saferace.names import GENERIC_SOURCE
from saferace.track import Track

#: What marks a submission as the filter protocol's (the drivers' have none).
PROTOCOL = "filters"


@dataclass(frozen=True)
class FilterEntry:
    """What a filter submission ranks: the ``filter`` (``none``, ``cbf``, ``mpsf`` or
    ``MODULE:FACTORY``) with our filters' ``gains`` and ``slack`` where set, fed by
    ``perception`` in the perceived conditions."""

    filter: str
    perception: str = GENERIC_SOURCE
    gains: str | None = None
    slack: str | None = None

    def __post_init__(self) -> None:
        if users_filter(self.filter) and (self.gains or self.slack):
            raise SafeRaceError(
                f"--filter-gains and --filter-slack are our filters' settings, not of {self.filter}"
            )
        for condition in load_filter_suite().conditions.values():
            self.config(condition)  # refuses settings that do not go together, now

    @property
    def label(self) -> str:
        """The entry in words: ``cbf (paper gains) fed generic``."""
        settings = [f"{self.gains} gains"] if self.gains else []
        settings += [f"{self.slack} slack"] if self.slack else []
        name = f"{self.filter} ({', '.join(settings)})" if settings else self.filter
        return name if self.filter == "none" else f"{name} fed {self.perception}"

    def config(self, condition: Condition) -> FilterConfig:
        """The filter settings of a run under ``condition``."""
        if self.filter == "none":
            return FilterConfig()
        options: dict = {"kind": self.filter}
        options.update({"gains": self.gains} if self.gains else {})
        options.update({"slack": self.slack} if self.slack else {})
        if condition.state == "noisy":
            options["state_noise"] = condition.noise
        elif condition.state == "perceived":
            options["state_source"] = self.perception
        return FilterConfig(**options)


def drive_filter_run(entry: FilterEntry, spec: FilterRunSpec, suite: FilterSuite) -> dict:
    """The row of one run: its measurements and score (see :mod:`filter_suite`)."""
    condition = suite.conditions[spec.condition]
    track_argument = suite.track_argument(spec.track)
    length_m = Track.load(track_argument).length_m
    env_kwargs: dict = {}
    if condition.randomize is not None:
        env_kwargs["randomize"] = condition.randomize
    if condition.faults:
        env_kwargs["faults"] = list(condition.faults)
    if spec.opponents is not None:
        env_kwargs["opponents"] = list(suite.opponents[spec.opponents])
        env_kwargs["terminate_on_collision"] = False
    env = make_task_env(
        suite.task_of(spec), track_argument, suite.laps, entry.config(condition), suite.seed,
        max_steps=max_steps_for(suite.max_seconds), **env_kwargs,
    )  # fmt: skip
    progress_m = [0.0]
    try:
        driver = make_agent(spec.driver, env, seed=suite.seed)
        result = run_episode(
            env,
            driver,
            seed=suite.seed,
            on_step=lambda obs, info, action: progress_m.__setitem__(0, info["progress_m"]),
        )
    finally:
        env.close()
    summary = result.summary
    completion = min(1.0, max(0.0, progress_m[0]) / (suite.laps * length_m))
    measurements = {
        **episode_measurements(result, completion, racing_env(env).control_dt_s),
        "clipped_steps": summary.get("clipped_steps"),
        "coverage": summary.get("coverage"),
        "filter_error": result.filter_error,
    }
    return {
        "filter_suite_version": suite.version,
        **asdict(spec),
        **measurements,
        **scored_filter_run(measurements, spec, suite),
    }


def filter_run_words(row: dict) -> str:
    """A run's key numbers, as its progress line says them."""
    words = (
        f"score {100.0 * row['score']:.1f}, completion {100.0 * row['completion']:.0f}%, "
        f"{row['time_outside_lane_s']:.2f} s outside, "
        + standstill_words(row.get("longest_standstill_s"))
    )
    collisions = row.get("at_fault_collisions")
    if collisions:
        words += f", {collisions} at-fault collision{'' if collisions == 1 else 's'}"
    if row["filter_error"] is not None:
        words += f"; {row['filter_error']}"
    return words


def entry_files(entry: FilterEntry) -> list[Path]:
    """The files an entry loads besides SafeRace itself: a filter's or a perception's
    module, a learned source's checkpoint, the generic model it is fed (none for ``none``,
    nor for our filters fed nothing of a file)."""
    files = agent_files(entry.filter) if users_filter(entry.filter) else []
    if entry.filter == "none":
        return files
    kind, _, argument = entry.perception.partition(":")
    if users_perception(entry.perception):
        return files + agent_files(entry.perception)
    if kind == GENERIC_SOURCE:
        from saferace.learning.perception import model_path, recipe_named

        return [*files, model_path(recipe_named(entry.perception))]
    if kind in STATE_SOURCE_FACTORIES:
        return [*files, Path(argument)]
    raise SafeRaceError(f"unknown perception {entry.perception!r}")


def filter_replay_record(entry: FilterEntry) -> dict:
    """What ``saferace verify`` needs to drive the entry again: the entry, the sha256 of
    every file it loads and one hash of them all, where its networks ran, the car's
    parameters' sha256."""
    files = {}
    for path in entry_files(entry):
        if not path.is_file():
            raise SafeRaceError(f"{entry.label} loads {path}, which is not there")
        files[str(path)] = file_sha256(path)
    identity = json.dumps({"entry": asdict(entry), "files": files}, sort_keys=True)
    return {
        "entry": asdict(entry),
        "files_sha256": files,
        "entry_sha256": hashlib.sha256(identity.encode()).hexdigest(),
        **network_settings(bool(files)),
        "vehicle_params_sha256": vehicle_params_sha256(),
    }


def run_filter_benchmark(
    entry: FilterEntry,
    out: str | Path,
    workers: int = 1,
    progress: bool = True,
    suite: FilterSuite | None = None,
    runs: Iterable[FilterRunSpec] | None = None,
    ray_address: str | None = None,
    circuits: str | Path | None = None,
) -> dict:
    """Run the protocol's runs missing from ``OUT.runs.jsonl`` (over ``workers``
    processes, or as Ray tasks with ``ray_address``; with the circuits' runs where
    ``circuits`` is their folder), then write the submission ``out``; the submission."""
    suite = suite or load_filter_suite()
    if circuits is not None:
        suite = suite.with_circuits(circuits)
    out = Path(out)
    journal = out.with_name(out.name + ".runs.jsonl")
    done = read_jsonl(journal) if journal.exists() else []
    replay = filter_replay_record(entry)
    for row in done:
        if row.get("entry_sha256") != replay["entry_sha256"]:
            raise SafeRaceError(
                f"{journal} holds runs of another entry, or of other files (entry hash "
                f"{row.get('entry_sha256')}, now {replay['entry_sha256']}): use another --out"
            )
    rows = journaled_runs(
        journal,
        done,
        list(runs) if runs is not None else suite.runs(),
        drive_filter_run,
        lambda spec: (entry, spec, suite),
        lambda row, spec: {"key": spec.key, "entry_sha256": replay["entry_sha256"], **row},
        filter_run_words,
        f"filter benchmark {entry.label}",
        (workers, ray_address, progress),
    )
    result = filter_submission(entry, rows, suite, replay)
    write_submission(out, result)
    return result


def filter_submission(
    entry: FilterEntry, rows: list[dict], suite: FilterSuite, replay: dict
) -> dict:
    """The submission of ``entry``: its rows, totals, the folder of the circuits it drove
    (None: none), how to replay it and where it was measured."""
    return {
        "protocol": PROTOCOL,
        "filter_suite_version": suite.version,
        "circuits": None if suite.circuits_folder is None else str(suite.circuits_folder),
        "entry": entry.label,
        **filter_totals(rows, suite),
        "rows": rows,
        "replay": replay,
        **provenance(),
    }
