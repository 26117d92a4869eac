"""The SafeRace benchmark: a fixed, versioned evaluation protocol and its submissions.

Protocol v1 (``saferace/assets/benchmark/v1/suite.json``, made by
``scripts/make_benchmark_suite.py``): the four built-in tracks and two evaluation tracks
generated once from fixed seeds and shipped with the suite (no other code of the
repository loads them, so nothing trains on them); both tasks; seeds 0 and 1, starting on
the start line and half a lap on; one lap within 60 s; each run without and with the shared
safety filter (``FilterConfig(kind="cbf")``: the default gains, the true lane state, as a
car with localisation would have it). 48 runs per agent.

Per run: completion (share of the lap driven), lap time and its ratio to the expert MPC's
on the same track, task and start (measured once and stored in the suite), mean deviation
from the reference, time outside the lane, the longest standstill while the driver asked
to move (``longest_standstill_s``, reported beside the score, not part of it), and with
the filter its interventions and correction sizes. The run's score (0 to 1, more is
better):

    score = completion * speed_ratio * exp(-time_outside_lane_s / 1 s)

with ``speed_ratio`` the run's mean speed over the expert's on that lap (faster than the
expert scores above 1). The agent's **score** is 100 times the mean over its unfiltered runs:
the filter cannot lift it. Beside it: the score with the filter, and the filter's share of
interventions and mean corrections in the filtered runs (how much the driver leans on it).
Every row carries the suite's version; changing the suite means a new version.

Protocol v2 adds a **traffic set** (``suite.json``'s ``traffic``): ``Overtake`` on the same
tracks, 2 m behind each of a fixed set of opponents (the expert MPC at 80% of the racing
line's speed, and a car at 80% that brakes as hard as it can every few seconds), from the
first start, two laps within 60 s, without and with the filter (which then keeps clear of
the opponents too). A run goes on after a collision. Its score is the lane score times
the suite's ``collision_factor`` (0.6) per collision the agent caused (multiplicative, as
the CARLA leaderboard's infraction penalties), its speed measured against the expert's lap alone on
the track; it also counts ``overtakes``, the opponents it passed and stayed ahead of. The agent's
**score** covers both sets; beside it, the traffic score and the at-fault collisions.
Submissions are checked and scored under the version they were made for, while it ships.

A submission may drive the protocol under sensor and actuator faults (``--faults``, see
:mod:`saferace.faults`): every run with the same faults, named in its replay record and
its agent hash, so that it is verified with them and ranked only beside submissions of
the same faults.
"""

from __future__ import annotations

import json
import math
import os
import platform
import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from saferace.envs.unwrap import racing_env
from saferace.errors import SafeRaceError
from saferace.eval.agents import make_agent
from saferace.eval.filters import FilterConfig
from saferace.eval.metrics import thinned_trajectory
from saferace.eval.runner import (
    EpisodeResult,
    git_revision,
    make_task_env,
    max_steps_for,
    package_versions,
    read_jsonl,
    run_episode,
    standstill_words,
)
from saferace.experiments.journal import journaled_runs
from saferace.experiments.replay_record import replay_faults, replay_record
from saferace.track import Track
from saferace.version import __version__

SUITE_VERSION = 2
OUTSIDE_SCALE_S = 1.0  # the score falls by 1/e per second outside the lane
TRAJECTORY_POINTS = 200
#: The traffic set's reference: the expert alone on the track, on this task's line.
TRAFFIC_REFERENCE_TASK = "RacingLine"
#: A traffic run's own measurements (None in a lane run).
TRAFFIC_MEASUREMENTS = ("collisions", "at_fault_collisions", "overtakes")
#: A submission's totals over the traffic runs (in suites with a traffic set).
TRAFFIC_TOTALS = (
    "traffic_score",
    "at_fault_collisions",
    "at_fault_collisions_with_filter",
    "overtakes",
)


@dataclass(frozen=True)
class TrafficSet:
    """The head-to-head runs of a suite: ``task`` among each named set of ``opponents``
    (specs as ``saferace drive --opponents`` takes them), from the suite's starts of
    ``seeds``, ``laps`` within ``max_seconds``; each at-fault collision multiplies the run's
    score by ``collision_factor``."""

    task: str
    opponents: dict[str, tuple[str, ...]]
    seeds: tuple[int, ...]
    laps: int
    max_seconds: float
    collision_factor: float


@dataclass(frozen=True)
class Suite:
    """A version of the protocol: what is driven, and the expert's reference lap times
    (``"track/task/seed"`` -> s)."""

    version: int
    tracks: tuple[str, ...]
    tasks: tuple[str, ...]
    seeds: tuple[int, ...]
    start_fractions: tuple[float, ...]  # of the lap, per seed
    laps: int
    max_seconds: float
    filters: tuple[str, ...]
    expert_lap_time_s: dict[str, float]
    folder: Path
    traffic: TrafficSet | None = None

    def track_argument(self, track: str) -> str:
        """A built-in track's name, or the path of one of the suite's own tracks."""
        path = self.folder / f"{track}.csv"
        return str(path) if path.exists() else track

    def runs(self) -> list[RunSpec]:
        """Every run of the protocol: the lane set's, then the traffic set's."""
        lane = [
            RunSpec(track, task, seed, kind)
            for track in self.tracks
            for task in self.tasks
            for seed in self.seeds
            for kind in self.filters
        ]
        traffic = self.traffic
        if traffic is None:
            return lane
        return lane + [
            RunSpec(track, traffic.task, seed, kind, opponents)
            for track in self.tracks
            for opponents in traffic.opponents
            for seed in traffic.seeds
            for kind in self.filters
        ]

    def laps_of(self, spec: RunSpec) -> int:
        return self.laps if spec.opponents is None else self.traffic_set().laps

    def max_seconds_of(self, spec: RunSpec) -> float:
        return self.max_seconds if spec.opponents is None else self.traffic_set().max_seconds

    def start_fraction(self, spec: RunSpec) -> float:
        """Where on the lap the run starts (a share of the lap), by its seed."""
        return self.start_fractions[self.seeds.index(spec.seed)]

    def reference_key(self, spec: RunSpec) -> str:
        """The key of the run's expert lap time in ``expert_lap_time_s``."""
        task = spec.task if spec.opponents is None else TRAFFIC_REFERENCE_TASK
        return f"{spec.track}/{task}/{spec.seed}"

    def traffic_set(self) -> TrafficSet:
        if self.traffic is None:
            raise SafeRaceError(f"suite v{self.version} has no traffic runs")
        return self.traffic


@dataclass(frozen=True)
class RunSpec:
    """One run of the protocol."""

    track: str
    task: str
    seed: int
    filter: str
    opponents: str | None = None  # the name of a traffic set's opponents

    @property
    def key(self) -> str:
        key = f"{self.track}/{self.task}/{self.seed}/{self.filter}"
        return key if self.opponents is None else f"{key}/{self.opponents}"

    @classmethod
    def of_row(cls, row: dict) -> RunSpec:
        """The run a result row (or a submission's) was driven for."""
        opponents = row.get("opponents")
        return cls(
            str(row["track"]),
            str(row["task"]),
            row["seed"],
            str(row["filter"]),
            None if opponents is None else str(opponents),
        )


def suite_folder(version: int = SUITE_VERSION) -> Path:
    return Path(str(resources.files("saferace.assets").joinpath(f"benchmark/v{version}")))


def load_suite(version: int = SUITE_VERSION) -> Suite:
    """The protocol of ``version`` as shipped in the package."""
    folder = suite_folder(version)
    path = folder / "suite.json"
    if not path.exists():
        raise SafeRaceError(f"no benchmark suite version {version} in this SafeRace ({path})")
    data = json.loads(path.read_text())
    traffic = data.get("traffic")
    return Suite(
        version=data["version"],
        tracks=tuple(data["tracks"]),
        tasks=tuple(data["tasks"]),
        seeds=tuple(data["seeds"]),
        start_fractions=tuple(data["start_fractions"]),
        laps=data["laps"],
        max_seconds=data["max_seconds"],
        filters=tuple(data["filters"]),
        expert_lap_time_s=data["expert_lap_time_s"],
        folder=folder,
        traffic=None
        if traffic is None
        else TrafficSet(
            task=traffic["task"],
            opponents={name: tuple(specs) for name, specs in traffic["opponents"].items()},
            seeds=tuple(traffic["seeds"]),
            laps=traffic["laps"],
            max_seconds=traffic["max_seconds"],
            collision_factor=traffic["collision_factor"],
        ),
    )


def drive_run(
    agent: str, spec: RunSpec, suite: Suite, mc_samples: int = 10, faults: tuple[str, ...] = ()
) -> dict:
    """The row of one run under ``faults``: its metrics and score (see the module
    docstring)."""
    track_argument = suite.track_argument(spec.track)
    length_m = Track.load(track_argument).length_m
    start_s_m = suite.start_fraction(spec) * length_m
    laps = suite.laps_of(spec)
    env_kwargs: dict = {"faults": list(faults)} if faults else {}
    if spec.opponents is not None:
        env_kwargs["opponents"] = list(suite.traffic_set().opponents[spec.opponents])
        env_kwargs["terminate_on_collision"] = False
    env = make_task_env(
        spec.task,
        track_argument,
        laps,
        FilterConfig(kind=spec.filter),
        spec.seed,
        max_steps=max_steps_for(suite.max_seconds_of(spec)),
        start_s_m=start_s_m,
        **env_kwargs,
    )
    progress_m = [0.0]
    try:
        driver = make_agent(agent, env, mc_samples=mc_samples, seed=spec.seed)
        result = run_episode(
            env,
            driver,
            seed=spec.seed,
            on_step=lambda obs, info, action: progress_m.__setitem__(0, info["progress_m"]),
        )
    finally:
        env.close()
    completion = min(1.0, max(0.0, progress_m[0]) / (laps * length_m))
    measurements = episode_measurements(result, completion, racing_env(env).control_dt_s)
    return {
        "suite_version": suite.version,
        **asdict(spec),
        **measurements,
        **scored(measurements, spec, suite),
    }


def episode_measurements(result: EpisodeResult, completion: float, control_dt_s: float) -> dict:
    """A protocol run's measurements of its episode ``result`` that covered ``completion``
    of its laps: laps, times, deviation, time outside, standstill, the filter's
    interventions and corrections, the traffic counts and the thinned trajectory."""
    summary = result.summary
    return {
        "completion": completion,
        "laps_completed": summary["laps_completed"],
        "lap_time_s": summary["mean_lap_time_s"],
        "driven_s": len(result.steps["time_s"]) * control_dt_s,
        "mean_abs_deviation_m": summary["mean_abs_deviation_m"],
        "time_outside_lane_s": summary["time_outside_lane_s"],
        "longest_standstill_s": summary["longest_standstill_s"],
        "terminated": result.terminated,
        "intervention_rate": summary.get("intervention_rate"),
        "mean_steer_correction_rad": summary.get("mean_steer_correction_rad"),
        "mean_accel_correction_mps2": summary.get("mean_accel_correction_mps2"),
        **{name: summary.get(name) for name in TRAFFIC_MEASUREMENTS},
        "trajectory": thinned_trajectory(
            result.steps, ("x_m", "y_m"), decimals=3, points=TRAJECTORY_POINTS
        ),
    }


def run_words(row: dict) -> str:
    """A run's key numbers, as its progress line says them (its score on the totals' scale
    of 100)."""
    words = (
        f"score {100.0 * row['score']:.1f}, completion {100.0 * row['completion']:.0f}%, "
        f"{row['time_outside_lane_s']:.2f} s outside, "
        + standstill_words(row.get("longest_standstill_s"))
    )
    collisions = row.get("at_fault_collisions")
    if collisions is not None:
        words += f", {collisions} at-fault collision{'' if collisions == 1 else 's'}"
    return words


def scored(measurements: dict, spec: RunSpec, suite: Suite) -> dict:
    """A run's derived fields from its measurements and the suite's expert reference (never
    from a reference or score carried in a row): its lap-time and speed ratios and score."""
    expert_lap_s = suite.expert_lap_time_s[suite.reference_key(spec)]
    completion, driven_s = measurements["completion"], measurements["driven_s"]
    lap_time_s = measurements["lap_time_s"]
    laps = suite.laps_of(spec)
    speed_ratio = completion * laps * expert_lap_s / driven_s if driven_s else 0.0
    outside_s = measurements["time_outside_lane_s"]
    score = completion * speed_ratio * math.exp(-outside_s / OUTSIDE_SCALE_S)
    if spec.opponents is not None:
        score *= suite.traffic_set().collision_factor ** measurements["at_fault_collisions"]
    return {
        "expert_lap_time_s": expert_lap_s,
        "lap_time_ratio": None if lap_time_s is None else lap_time_s / expert_lap_s,
        "speed_ratio": speed_ratio,
        "score": score,
    }


def run_benchmark(
    agent: str,
    out: str | Path,
    workers: int = 1,
    mc_samples: int = 10,
    progress: bool = True,
    suite: Suite | None = None,
    runs: Iterable[RunSpec] | None = None,
    ray_address: str | None = None,
    faults: Iterable[str] = (),
) -> dict:
    """Run the protocol's runs missing from ``OUT.runs.jsonl`` (over ``workers``
    processes, or as Ray tasks with ``ray_address``: ``"local"`` starts a Ray instance on
    this machine) under ``faults``, then write the submission ``out``; the submission."""
    suite = suite or load_suite()
    out = Path(out)
    journal = out.with_name(out.name + ".runs.jsonl")
    done = read_jsonl(journal) if journal.exists() else []
    replay = replay_record(agent, mc_samples, faults)
    for row in done:
        if row.get("agent") != agent or row.get("suite_version") != suite.version:
            raise SafeRaceError(
                f"{journal} holds runs of agent {row.get('agent')!r} on suite "
                f"v{row.get('suite_version')}, not {agent!r} on v{suite.version}: use another --out"
            )
        if row.get("agent_sha256") != replay["agent_sha256"]:
            raise SafeRaceError(
                f"{journal} holds runs of {agent!r} with other files or settings (agent hash "
                f"{row.get('agent_sha256')}, now {replay['agent_sha256']}): use another --out"
            )
    rows = journaled_runs(
        journal,
        done,
        list(runs) if runs is not None else suite.runs(),
        drive_run,
        lambda spec: (agent, spec, suite, mc_samples, replay_faults(replay)),
        lambda row, spec: _keyed(row, replay, spec),
        run_words,
        f"benchmark {agent}",
        (workers, ray_address, progress),
    )
    result = submission(agent, rows, suite, replay)
    write_submission(out, result)
    return result


def write_submission(out: Path, result: dict) -> None:
    """Write ``result`` to ``out`` at once (through a partial file: never half of it)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(f".{out.name}.partial")
    partial.write_text(json.dumps(result, indent=1) + "\n")
    os.replace(partial, out)


def _keyed(row: dict, replay: dict, spec: RunSpec) -> dict:
    return {
        "key": spec.key,
        "agent": replay["agent"],
        "agent_sha256": replay["agent_sha256"],
        **row,
    }


def totals(rows: list[dict], suite: Suite) -> dict:
    """The agent's scores and totals from its rows' scores (see the module docstring), the
    traffic totals where ``suite`` has a traffic set."""
    plain = [row for row in rows if row["filter"] == "none"]
    filtered = [row for row in rows if row["filter"] != "none"]
    rates = [row["intervention_rate"] for row in filtered if row["intervention_rate"] is not None]
    result = {
        "score": _percent(plain),
        "score_with_filter": _percent(filtered),
        "intervention_rate": float(np.mean(rates)) if rates else None,
        "completion": float(np.mean([row["completion"] for row in plain])) if plain else None,
        "time_outside_lane_s": float(sum(row["time_outside_lane_s"] for row in plain)),
    }
    if suite.traffic is None:
        return result
    traffic = [row for row in plain if row.get("opponents") is not None]
    traffic_filtered = [row for row in filtered if row.get("opponents") is not None]
    values = (
        _percent(traffic),
        _total(traffic, "at_fault_collisions"),
        _total(traffic_filtered, "at_fault_collisions"),
        _total(traffic, "overtakes"),
    )
    return {**result, **dict(zip(TRAFFIC_TOTALS, values, strict=True))}


def _percent(rows: list[dict]) -> float | None:
    """100 times the mean score of ``rows`` (None for none)."""
    return 100.0 * float(np.mean([row["score"] for row in rows])) if rows else None


def _total(rows: list[dict], name: str) -> int | None:
    return sum(row[name] for row in rows) if rows else None


def submission(agent: str, rows: list[dict], suite: Suite, replay: dict) -> dict:
    """The submission of ``agent``: its rows, scores, how to replay it and where it was
    measured."""
    return {
        "suite_version": suite.version,
        "agent": agent,
        **totals(rows, suite),
        "rows": rows,
        "replay": replay,
        **provenance(),
    }


def provenance() -> dict:
    """Where a submission was measured: the versions, git revision, machine and time."""
    return {
        "versions": {"saferace": __version__, **package_versions()},
        "git_revision": git_revision(),
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
        },
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
