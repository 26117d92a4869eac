"""The one episode runner: any agent on any task, with per-step records and lap metrics."""

from __future__ import annotations

import hashlib
import json
import logging
import platform
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache, partial
from importlib import metadata
from pathlib import Path
from typing import Any, BinaryIO

import gymnasium as gym
import numpy as np

from saferace.envs.racing_env import DEFAULT_CONTROL_HZ
from saferace.envs.unwrap import racing_env
from saferace.errors import SafeRaceError
from saferace.eval.agents import act, make_agent
from saferace.eval.filters import FilterConfig, apply_filter, has_safety_filter
from saferace.eval.metrics import (
    SAFETY_FIELDS,
    STEP_FIELDS,
    TRAFFIC_FIELDS,
    LapMetrics,
    lap_metrics,
    safety_step_record,
    summarize,
    thinned_trajectory,
    traffic_paths,
    traffic_step_record,
    traffic_summary,
)
from saferace.names import TASK_IDS as LANE_TASK_IDS
from saferace.names import TRAFFIC_TASK_IDS
from saferace.progress import Progress
from saferace.safety.decision import nominal_parts
from saferace.track import Track, builtin_track_names
from saferace.version import __version__

TASK_IDS = {**LANE_TASK_IDS, **TRAFFIC_TASK_IDS}
LOG = logging.getLogger(__name__)
RECORDED_PACKAGES = ("mujoco", "numpy", "osqp", "gymnasium", "torch", "torchvision")


@dataclass
class EpisodeResult:
    """Per-step arrays, per-lap metrics, the episode's end and, in traffic, its counts."""

    steps: dict[str, np.ndarray]
    laps: list[LapMetrics]
    terminated: bool
    truncated: bool
    traffic: dict[str, int] | None = None
    #: Its state source's description at the end, where it ran in another process.
    source_description: dict | None = None
    #: How it ended, in words (:func:`episode_ending`).
    ending: str = ""
    #: What a filter of the protocol raised, where that ended it.
    filter_error: str | None = None

    @property
    def summary(self) -> dict:
        """Lap metrics over the episode, and in traffic its collisions and overtakes."""
        return {**summarize(self.laps), **(self.traffic or {})}


def task_id(task: str) -> str:
    """Gymnasium id of ``CenterLine``, ``RacingLine`` or ``Overtake`` (or a full id)."""
    if task in TASK_IDS.values():
        return task
    if task not in TASK_IDS:
        raise ValueError(f"unknown task {task!r}: use one of {', '.join(TASK_IDS)}")
    return TASK_IDS[task]


def max_steps_for(seconds: float | None, control_hz: float = DEFAULT_CONTROL_HZ) -> int | None:
    """The step limit of an episode of ``seconds`` simulated time (None: the task's own)."""
    if seconds is None:
        return None
    if seconds <= 0:
        raise SafeRaceError(f"an episode's time limit must be positive, got {seconds} s")
    return round(seconds * control_hz)


def run_episode(
    env: gym.Env,
    agent,
    seed: int | None = None,
    progress: bool = False,
    on_step: Callable[[dict, dict, np.ndarray], None] | None = None,
) -> EpisodeResult:
    """Drive ``agent`` until the episode ends; record STEP_FIELDS after every step.

    Also recorded: the true lane barrier ``lane_barrier_m``; in traffic the
    :data:`TRAFFIC_FIELDS`; and, if ``env`` is wrapped in a
    :class:`~saferace.safety.cbf.filter.SafetyFilter` or a filter of the protocol
    (:mod:`saferace.safety.filter_protocol`), the :data:`SAFETY_FIELDS`. An agent may
    return a :class:`~saferace.safety.decision.NominalAction`; without a filter its mean is
    applied. ``on_step(observation, info, action)`` is called after each step with the
    action applied (videos, recordings).
    """
    observation, info = env.reset(seed=seed)
    if hasattr(agent, "reset"):
        agent.reset()
    recorder = EpisodeRecorder(env)
    terminated = truncated = False
    base = racing_env(env)
    with Progress(base.max_steps, base.track.name, "step", enabled=progress) as bar:
        while not (terminated or truncated):
            action = act(agent, observation, info)
            if not recorder.filtered:
                action = nominal_parts(action)[0]
            observation, _, terminated, truncated, info = env.step(action)
            recorder.record(info)
            if on_step is not None:
                applied = info["safety"]["filtered_action"] if recorder.filtered else action
                on_step(observation, info, np.asarray(applied, dtype=float))
            bar.update()
            if bar.terminal:  # not formatted every step where nothing shows it
                bar.show(f"lap={info['lap']}, v={info['v_x_mps']:.1f}m/s")
        result = recorder.result(info, terminated, truncated)
        words = episode_words(result.summary, result.ending)
        bar.report(f"episode (seed {seed})", words, time_left=False)
    return result


class EpisodeRecorder:
    """One episode's per-step records (what :func:`run_episode` keeps) and its result.

    ``env`` tells what to record: the :data:`STEP_FIELDS` and the true lane barrier
    always, the :data:`TRAFFIC_FIELDS` in traffic, the :data:`SAFETY_FIELDS` behind a
    :class:`~saferace.safety.cbf.filter.SafetyFilter`.
    """

    def __init__(self, env: gym.Env) -> None:
        base = racing_env(env)
        self.filtered = has_safety_filter(env)
        self.in_traffic = base.traffic is not None
        self.half_width_m = base.car_half_width_m
        self.control_dt_s = base.control_dt_s
        self.max_laps = base.max_laps
        fields = (
            STEP_FIELDS
            + ("lane_barrier_m",)
            + (TRAFFIC_FIELDS if self.in_traffic else ())
            + (SAFETY_FIELDS if self.filtered else ())
        )
        self.records: dict[str, list] = {name: [] for name in fields}

    def record(self, info: dict[str, Any]) -> None:
        """Keep one step's ``info``."""
        records = self.records
        for name in STEP_FIELDS:
            records[name].append(info[name])
        records["lane_barrier_m"].append(
            min(info["w_left_m"] - info["e_y_m"], info["w_right_m"] + info["e_y_m"])
            - self.half_width_m
        )
        if self.in_traffic:
            for name, value in traffic_step_record(info).items():
                records[name].append(value)
        if self.filtered:
            for name, value in safety_step_record(info["safety"]).items():
                records[name].append(value)

    def result(self, last_info: dict[str, Any], terminated: bool, truncated: bool) -> EpisodeResult:
        """The episode's result, ``last_info`` its last step's."""
        steps = {name: np.asarray(values) for name, values in self.records.items()}
        laps = lap_metrics(steps, last_info["lap_times_s"], self.control_dt_s)
        traffic = traffic_summary(steps) if self.in_traffic else None
        ending = episode_ending(last_info, terminated, self.max_laps, self.filtered)
        return EpisodeResult(
            steps, laps, terminated, truncated, traffic, ending=ending,
            filter_error=last_info.get("filter_error"),
        )  # fmt: skip


#: Below this speed (m/s) a car at the end of a run behind a filter stands.
STANDING_MPS = 0.1


def episode_ending(
    last_info: dict[str, Any], terminated: bool, max_laps: int, filtered: bool
) -> str:
    """How a run ended, from its last step: its filter raised, its laps done, the car out of
    its lane, flipped or in a collision (terminated), or the time limit (and, behind a
    filter, the car standing there: what a filter that stopped it looks like)."""
    laps = int(last_info["lap"])
    if "filter_error" in last_info:
        return f"ended: {last_info['filter_error']}"
    if terminated:
        if last_info.get("fully_outside_lane"):
            return f"ended: the car left its lane at {last_info['time_s']:.2f} s"
        if last_info.get("at_fault_collisions", 0) > 0:
            return f"ended: a collision the car caused at {last_info['time_s']:.2f} s"
        return f"ended: the car flipped at {last_info['time_s']:.2f} s"
    if laps >= max_laps:
        return f"ended: {laps} of {max_laps} laps done"
    standing = filtered and abs(float(last_info["v_x_mps"])) < STANDING_MPS
    return f"ended: the time limit, {laps} of {max_laps} laps done" + (
        ", the car standing (stopped by the filter)" if standing else ""
    )


def episode_words(summary: dict, ending: str = "") -> str:
    """An episode's key numbers, as its progress line says them: laps completed, time
    outside the lane and beside it the longest standstill (:func:`standstill_words`), and
    how it ended (:func:`episode_ending`)."""
    lap = summary.get("mean_lap_time_s")
    return (
        f"{summary['laps_completed']} laps"
        + (f" of {lap:.2f} s" if lap is not None else "")
        + f", {summary['time_outside_lane_s']:.2f} s outside, "
        + standstill_words(summary.get("longest_standstill_s"))
        + (f"; {ending}" if ending else "")
    )


def standstill_words(seconds: float | None) -> str:
    """The longest standstill while the driver asked to move, in words (``-`` where it was
    not recorded): what keeps a car that never left the lane by standing still visible."""
    return "longest standstill " + ("-" if seconds is None else f"{seconds:.2f} s")


def evaluate(
    agent_spec: str,
    task: str,
    track: str,
    seeds: list[int],
    laps: int = 1,
    model: str = "dynamic",
    out: str | Path | None = None,
    progress: bool = True,
    env_kwargs: dict[str, Any] | None = None,
    safety: FilterConfig | None = None,
    mc_samples: int = 10,
    num_envs: int = 1,
) -> list[dict]:
    """One JSON row per seed: metrics, trajectory, configuration, versions; appended to ``out``.

    ``safety`` wraps the agent in a safety filter. Rows are written as each episode ends
    (``num_envs`` > 1: as each group of that many, driven at once, ends; see
    :func:`~saferace.eval.vector_runner.run_together`), so an interrupted run keeps what it
    finished. A learned agent or state source is recorded by its checkpoint
    (``agent_checkpoint``, ``state_source``).
    """
    safety = safety or FilterConfig()
    env_kwargs = env_kwargs or {}
    rows = []
    for start in range(0, len(seeds), num_envs):
        group = list(seeds[start : start + num_envs])
        env = make_task_env(task, track, laps, safety, group[0], **env_kwargs)
        try:
            agents = [
                make_agent(agent_spec, env, model=model, mc_samples=mc_samples, seed=seed)
                for seed in group
            ]
            if len(group) == 1:
                results = [run_episode(env, agents[0], seed=group[0], progress=progress)]
            else:
                from saferace.eval.vector_runner import run_together

                make_envs = [
                    partial(make_task_env, task, track, laps, safety, seed, **env_kwargs)
                    for seed in group
                ]
                results = run_together(make_envs, agents, group, env, progress=progress)
            for seed, agent, result in zip(group, agents, results, strict=True):
                row = result_row(
                    agent_spec, task, racing_env(env).track.name, track, seed, laps, model,
                    result, safety=safety,
                )  # fmt: skip
                row["config"]["env"] = env_kwargs
                if hasattr(agent, "describe"):
                    row["agent_checkpoint"] = agent.describe()
                describe_source = getattr(getattr(env, "state_source", None), "describe", None)
                if result.source_description is not None:
                    row["state_source"] = result.source_description
                elif describe_source is not None:
                    row["state_source"] = describe_source()
                if hasattr(agent, "stats"):
                    row["solver"] = solver_summary(agent.stats)
                if "solve_time_s" in result.steps:
                    row["filter_solver"] = _solve_times_ms(
                        result.steps["solve_time_s"], result.steps["filter_time_s"]
                    )
                rows.append(row)
                if out is not None:
                    append_jsonl(out, row)
        finally:
            env.close()
    return rows


def make_task_env(
    task: str, track: str, laps: int, safety: FilterConfig, seed: int | None, **env_kwargs
) -> gym.Env:
    """A task's env for ``laps`` laps of ``track``, behind the filter ``safety`` asks for."""
    env = gym.make(task_id(task), track=track, max_laps=laps, **env_kwargs)
    return apply_filter(env, safety, seed, timed=True)


def result_row(
    agent,
    task,
    track_name,
    track_arg,
    seed,
    laps,
    model,
    result: EpisodeResult,
    safety: FilterConfig | None = None,
) -> dict:
    """The JSON row of one evaluated episode behind the filter ``safety`` (None: none).

    The row says how the episode ended (``ending``) and, where a filter of the protocol
    raised, what (``filter_error``). It names its track so that it is found from any
    folder (:func:`track_reference`):
    ``config["track"]`` is a built-in track's name or a track file's absolute path, with
    ``config["track_sha256"]`` the file's content hash; ``config["track_given"]`` is the
    argument as given.
    """
    return {
        "agent": agent,
        "task": task,
        "track": track_name,
        "seed": seed,
        "filter": (safety or FilterConfig()).as_dict(),
        "summary": result.summary,
        "laps": [lap.as_dict() for lap in result.laps],
        "terminated": result.terminated,
        "ending": result.ending,
        **({} if result.filter_error is None else {"filter_error": result.filter_error}),
        "trajectory": thinned_trajectory(result.steps, ("x_m", "y_m", "s_m", "v_x_mps")),
        **({} if result.traffic is None else {"traffic": traffic_paths(result.steps)}),
        "config": {**track_reference(track_arg), "laps": laps, "model": model},
        "saferace_version": __version__,
        "git_revision": git_revision(),
        "packages": package_versions(),
        "python": platform.python_version(),
    }


def track_reference(track_arg: str | Path) -> dict:
    """How a row names its track: a built-in track by name; a track file by its absolute
    path and the sha256 of its content, so that the row finds it from any folder and a
    changed file is told apart (:func:`row_track`).

    Only the reference is kept, not the centre line's points: a row stays small (the safety
    table writes sixteen per track, and a real circuit has thousands of points), and the
    hash refuses a file that was edited after the run instead of drawing the run on a
    different track.
    """
    given = str(track_arg)
    if given in builtin_track_names():
        return {"track": given, "track_sha256": None, "track_given": given}
    path = Path(given).expanduser().resolve()
    digest = file_sha256(path) if path.is_file() else None
    return {"track": str(path), "track_sha256": digest, "track_given": given}


def file_sha256(path: str | Path) -> str:
    """The sha256 of a file's bytes, in hex."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def track_key(row: dict) -> tuple[str, str | None]:
    """What tells a row's track apart: its name or absolute path, and its content hash."""
    config = row.get("config", {})
    return str(config.get("track", row.get("track"))), config.get("track_sha256")


def row_track(row: dict, where: str = "a result row") -> Track:
    """The track a result row was driven on, from any working folder.

    A built-in name loads that track; a file is taken at the row's absolute path (or, for a
    row written before rows recorded one, its path as given, relative to the working
    folder) when its sha256 is the row's. Anything else is a :class:`SafeRaceError` naming
    ``where`` (the row), the path and the hash.
    """
    name, digest = track_key(row)
    if name in builtin_track_names():
        return Track.load(name)
    path = Path(name)
    if not path.is_file():
        if digest is None:
            raise SafeRaceError(
                f"{where}: its track file {name} is not found from {Path.cwd()}; the row was "
                "written before rows recorded absolute paths, so run this from the folder "
                "where it was evaluated, or evaluate again"
            )
        raise SafeRaceError(
            f"{where}: its track file {name} (sha256 {digest}) is gone; put that file back "
            "at that path, or evaluate again"
        )
    if digest is not None and (found := file_sha256(path)) != digest:
        raise SafeRaceError(
            f"{where}: the track file {name} has changed since the row was written: its "
            f"sha256 is {found}, the row's {digest}; restore the file the row was driven on, "
            "or evaluate again"
        )
    return Track.load(path)


def solver_summary(stats) -> dict:
    return {**_solve_times_ms(stats.solve_times_s, stats.step_times_s), "failures": stats.failures}


def _solve_times_ms(solve_times_s, step_times_s) -> dict[str, float]:
    """Median and 95th percentile of per-step solve times and of whole steps (a filter's:
    state, solve and decision), in ms."""
    return {
        "solve_median_ms": float(np.median(solve_times_s) * 1e3),
        "solve_p95_ms": float(np.percentile(solve_times_s, 95) * 1e3),
        "step_median_ms": float(np.median(step_times_s) * 1e3),
        "step_p95_ms": float(np.percentile(step_times_s, 95) * 1e3),
    }


def append_jsonl(path: str | Path, row: dict) -> None:
    """Append one row and flush it to disk; a torn last row (a write cut off by a kill) is
    dropped first, so that the rows written after it stay readable."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "ab+") as handle:
        _drop_torn_tail(handle)
        handle.write((json.dumps(row) + "\n").encode())
        handle.flush()


def _drop_torn_tail(handle: BinaryIO) -> None:
    """Truncate a file open for appending after its last newline."""
    size = handle.seek(0, 2)
    if not size:
        return
    handle.seek(size - 1)
    if handle.read(1) == b"\n":
        return
    handle.seek(0)
    handle.truncate(handle.read().rfind(b"\n") + 1)


def read_jsonl(path: str | Path) -> list[dict]:
    """Rows of a results file (blank lines skipped; a torn last row, a write cut off by a
    kill, is left out with a warning)."""
    with open(path) as handle:
        lines = handle.read().split("\n")
    rows = [json.loads(line) for line in lines[:-1] if line.strip()]
    if lines[-1].strip():
        try:
            rows.append(json.loads(lines[-1]))
        except json.JSONDecodeError:
            LOG.warning("%s: its last row was cut off (an interrupted run): left out", path)
    return rows


@cache
def git_revision() -> str | None:
    """The source's git revision, if SafeRace runs from a git checkout, with ``+dirty`` where
    its tracked files differ from it. Read once per process, when its first row is written
    (its code is loaded by then): a commit made while a long table runs does not change the
    code its workers run, and their rows say so."""
    revision = _git("rev-parse", "HEAD")
    if revision is None:
        return None
    return (
        f"{revision}+dirty" if _git("status", "--porcelain", "--untracked-files=no") else revision
    )


def _git(*args: str) -> str | None:
    """A git command's output in the package's folder (None where it fails or prints nothing)."""
    try:
        result = subprocess.run(
            ["git", *args],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return result.stdout.strip() or None


def package_versions() -> dict[str, str]:
    versions = {}
    for name in RECORDED_PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return versions
