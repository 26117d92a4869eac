"""How a driver holds up when the scene's look (and optionally the car) changes.

:func:`run_robustness` drives an agent once per domain-randomisation preset and seed (the
seed draws the look, see :mod:`saferace.envs.randomization`), optionally behind the safety
filter, and records per run: completion, lap time, time outside the lane, the longest
standstill while the driver asked to move, the filter's
interventions and, when a state network is in play (the filter's ``learned:CKPT`` state
source, or ``monitor_state_source`` beside an unfiltered run), its error against the true
lane state and the spread of its MC-dropout samples. Runs are appended to ``runs.jsonl``
as they end; a run already there is not driven again. :func:`robustness_rows` aggregates
them per preset, the table of ``saferace robustness``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from saferace.envs.unwrap import racing_env
from saferace.errors import SafeRaceError
from saferace.eval.agents import load_entry_point, make_agent
from saferace.eval.filters import STATE_SOURCE_FACTORIES
from saferace.eval.metrics import longest_standstill
from saferace.eval.runner import (
    append_jsonl,
    make_task_env,
    max_steps_for,
    read_jsonl,
    run_episode,
)
from saferace.eval.tables import markdown_table, or_dash, write_csv
from saferace.experiments.robustness_config import RobustnessConfig
from saferace.safety.uncertainty.conformal import MIN_SIGMA, clopper_pearson
from saferace.safety.uncertainty.intervals import state_interval
from saferace.track.track import Track

RUNS_FILE = "runs.jsonl"
TABLE_COLUMNS = (
    "look",
    "runs",
    "completion [%]",
    "laps completed",
    "lap time [s]",
    "time outside lane [s]",
    "longest standstill [s]",
    "interventions [%]",
    "e_y error [m]",
    "e_y spread [m]",
    "e_psi error [rad]",
    "e_psi spread [rad]",
    "truth within 2 spreads [%]",
    "coverage [%] (95% band)",
    "e_y half width [m]",
    "Gaussian NLL",
    "alarms [%]",
    "lowest lane barrier [m]",
)
#: The columns of the table by track and look (where a state source was scored): a pooled
#: coverage can hide a track the interval misses.
TRACK_COLUMNS = (
    "track",
    "look",
    "runs",
    "scored steps",
    "coverage [%] (95% band)",
    "alarms [%]",
    "completion [%]",
    "time outside lane [s]",
    "longest standstill [s]",
)


def run_robustness(
    config: RobustnessConfig, out_dir: str | Path, progress: bool = True
) -> list[dict]:
    """Drive every (preset, seed) not yet in ``out_dir/runs.jsonl``; all runs' rows."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    settings = json.loads(  # as read back from runs.jsonl: tuples become lists
        json.dumps(
            {k: v for k, v in config.as_dict().items() if k not in ("tracks", "presets", "seeds")}
        )
    )
    if not config.faults:  # as runs from before faults were an option read back
        del settings["faults"]
    path = out_dir / RUNS_FILE
    done = read_jsonl(path) if path.exists() else []
    for row in done:
        if row["settings"] != settings:
            raise SafeRaceError(
                f"{path} holds runs of other settings ({_difference(row['settings'], settings)}): "
                "use another --out"
            )
    made_of = {track: Track.load(track).fingerprint for track in config.tracks}
    finished = {_key(row) for row in done}
    wanted = [
        (t, made_of[t], p, s) for t in config.tracks for p in config.presets for s in config.seeds
    ]
    for key in wanted:
        if key in finished:
            continue
        track, fingerprint, preset, seed = key
        row = {
            "track": track,
            "track_fingerprint": fingerprint,
            "look": preset,
            "seed": seed,
            **drive_once(config, track, preset, seed, progress),
            "settings": settings,
        }
        append_jsonl(path, row)
        done.append(row)
    return [row for row in done if _key(row) in set(wanted)]


def _key(row: dict) -> tuple[str, str | None, str, int]:
    """A run's: its track by name and by content (a CSV edited under the same name is
    driven again), its look and its seed."""
    return row["track"], row.get("track_fingerprint"), row["look"], row["seed"]


def drive_once(
    config: RobustnessConfig, track: str, preset: str, seed: int, progress: bool
) -> dict:
    """One run's metrics on ``track`` in the look (and car) ``preset`` draws for ``seed``."""
    env = make_task_env(
        config.task,
        track,
        config.laps,
        config.safety,
        seed,
        max_steps=max_steps_for(config.max_seconds),
        image_size=(config.image_size, config.image_size),
        stereo=config.stereo,
        randomize=preset,
        physics_randomize=preset if config.physics else None,
        faults=list(config.faults),
    )
    try:
        monitor = _state_monitor(config, env, seed)
        progress_m = [0.0]

        def on_step(observation: dict, info: dict, action: np.ndarray) -> None:
            monitor(observation, info)
            progress_m[0] = info["progress_m"]  # since the reset

        agent = make_agent(
            config.agent, env, model=config.model, mc_samples=config.mc_samples, seed=seed
        )
        result = run_episode(env, agent, seed=seed, progress=progress, on_step=on_step)
        length = racing_env(env).track.length_m
    finally:
        env.close()
    summary = result.summary
    intervened = result.steps.get("intervened")
    return {
        "completion": min(1.0, progress_m[0] / (config.laps * length)),
        "laps_completed": summary["laps_completed"],
        "lap_time_s": summary["mean_lap_time_s"],
        "time_outside_lane_s": summary["time_outside_lane_s"],
        "longest_standstill_s": summary["longest_standstill_s"],
        "intervention_rate": None if intervened is None else float(np.mean(intervened)),
        "min_lane_barrier_m": summary["min_lane_barrier_m"],
        "alarm_rate": summary.get("alarm_rate"),
        "fallback_rate": summary.get("fallback_rate"),
        "terminated": result.terminated,
        **monitor.summary(),
    }


#: A state sample's view for the tables: mean, spread, truth, and the interval's bounds.
StateView = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
#: The interval of an unfiltered run's monitored source that knows none of its own.
MONITOR_Z = 1.96


class _StateErrors:
    """Collects a state network's samples and interval against the truth, step by step."""

    def __init__(self, sample: Callable[[dict, dict], StateView] | None):
        self.sample = sample
        self.views: list[StateView] = []

    def __call__(self, observation: dict, info: dict) -> None:
        if self.sample is not None:
            self.views.append(self.sample(observation, info))

    def summary(self) -> dict:
        """Errors and spreads of ``[e_y, e_psi]``, the Gaussian negative log-likelihood of
        the truth (summed over both), and the interval's coverage (of both) and width."""
        if not self.views:
            return {}
        mean, spread, truth, lower, upper = (
            np.array(part) for part in zip(*self.views, strict=True)
        )
        errors = np.abs(mean - truth)
        within = np.all(errors <= 2.0 * spread, axis=1)
        sigma = np.maximum(spread, MIN_SIGMA)
        nll = 0.5 * np.log(2.0 * np.pi * sigma**2) + 0.5 * (errors / sigma) ** 2
        covered = np.all((lower <= truth) & (truth <= upper), axis=1)
        return {
            "e_y_error_m": float(np.sqrt(np.mean(errors[:, 0] ** 2))),
            "e_y_spread_m": float(np.mean(spread[:, 0])),
            "e_psi_error_rad": float(np.sqrt(np.mean(errors[:, 1] ** 2))),
            "e_psi_spread_rad": float(np.mean(spread[:, 1])),
            "truth_within_2_spreads": float(np.mean(within)),
            "gaussian_nll": float(np.mean(nll.sum(axis=1))),
            "coverage": float(np.mean(covered)),
            "covered_steps": int(covered.sum()),
            "scored_steps": len(covered),
            "e_y_half_width_m": float(np.mean(0.5 * (upper[:, 0] - lower[:, 0]))),
        }


def _state_monitor(config: RobustnessConfig, env, seed: int) -> _StateErrors:
    """Scores the filter's learned state source, or a monitoring one, or nothing."""
    if config.safety.kind == "cbf" and config.safety.state_source is not None:

        def from_filter(observation: dict, info: dict) -> StateView:
            decision = info["safety"]  # the state the filter believed before this step
            return tuple(  # type: ignore[return-value]
                np.asarray(decision[name][:2])
                for name in ("state_mean", "state_std", "state_true", "state_lower", "state_upper")
            )

        return _StateErrors(from_filter)
    if config.monitor_state_source is None:
        return _StateErrors(None)
    kind, argument = config.monitor_state_source.split(":", 1)
    if kind not in STATE_SOURCE_FACTORIES:
        raise SafeRaceError(f"unknown state source {config.monitor_state_source!r}")
    factory = load_entry_point(STATE_SOURCE_FACTORIES[kind])
    image_shape = env.observation_space["image"].shape
    source = factory(argument, image_shape, n_samples=config.mc_samples, seed=seed)

    def from_monitor(observation: dict, info: dict) -> StateView:
        samples = np.atleast_2d(source.samples(observation, info))
        lower, upper = state_interval(source, samples, MONITOR_Z)
        truth = np.array([info["e_y_m"], info["e_psi_rad"]])
        mean, spread = samples.mean(axis=0), samples.std(axis=0)
        return mean[:2], spread[:2], truth, lower[:2], upper[:2]

    return _StateErrors(from_monitor)


def robustness_rows(runs: list[dict], presets: tuple[str, ...], laps: int = 1) -> list[list]:
    """One row of :data:`TABLE_COLUMNS` per look: means over its tracks and seeds (``laps``
    each), the pooled coverage, the lowest barrier, the longest standstill of any run;
    ``-`` where nothing was measured."""
    rows = []
    for preset in presets:
        mine = [run for run in runs if run["look"] == preset]
        if not mine:
            continue

        rows.append(
            [
                preset,
                len(mine),
                mean_of(mine, "completion", 100.0),
                f"{sum(run['laps_completed'] for run in mine)} of {laps * len(mine)}",
                mean_of(mine, "lap_time_s"),
                mean_of(mine, "time_outside_lane_s"),
                longest_of(mine),
                mean_of(mine, "intervention_rate", 100.0),
                mean_of(mine, "e_y_error_m"),
                mean_of(mine, "e_y_spread_m"),
                mean_of(mine, "e_psi_error_rad"),
                mean_of(mine, "e_psi_spread_rad"),
                mean_of(mine, "truth_within_2_spreads", 100.0),
                pooled_coverage(mine),
                mean_of(mine, "e_y_half_width_m"),
                mean_of(mine, "gaussian_nll"),
                mean_of(mine, "alarm_rate", 100.0),
                lowest_of(mine, "min_lane_barrier_m"),
            ]
        )
    return rows


def track_rows(runs: list[dict], presets: tuple[str, ...]) -> list[list]:
    """One row of :data:`TRACK_COLUMNS` per track and look whose runs scored a state
    source: the coverage of that track's steps with its band, the alarm rate, completion,
    time outside the lane and the longest standstill."""
    rows = []
    for track in dict.fromkeys(run["track"] for run in runs):
        for preset in presets:
            mine = [run for run in runs if run["track"] == track and run["look"] == preset]
            if not any(run.get("scored_steps") for run in mine):
                continue
            rows.append(
                [
                    Path(track).stem,
                    preset,
                    len(mine),
                    sum(run["scored_steps"] for run in mine),
                    pooled_coverage(mine),
                    mean_of(mine, "alarm_rate", 100.0),
                    mean_of(mine, "completion", 100.0),
                    mean_of(mine, "time_outside_lane_s"),
                    longest_of(mine),
                ]
            )
    return rows


def mean_of(runs: list[dict], name: str, scale: float = 1.0) -> float | str:
    """``scale`` times the mean of ``name`` over the runs that measured it; ``-`` if none."""
    values = [run[name] for run in runs if run.get(name) is not None]
    return scale * float(np.mean(values)) if values else "-"


def lowest_of(runs: list[dict], name: str) -> float | str:
    """The lowest ``name`` over the runs that measured it; ``-`` if none."""
    values = [run[name] for run in runs if run.get(name) is not None]
    return min(values) if values else "-"


def longest_of(runs: list[dict]) -> float | str:
    """The longest standstill while the driver asked to move of any of ``runs``; ``-``
    where a run predates the measurement (see :func:`~saferace.eval.metrics.
    longest_standstill`)."""
    return or_dash(longest_standstill(runs))


def pooled_coverage(runs: list[dict]) -> str:
    """The share of all scored steps of ``runs`` whose truth lay inside the interval, with
    its Clopper-Pearson 95% band (steps of one drive are not independent: the band is the
    steps' own, narrower than the drives' would be)."""
    covered = sum(run.get("covered_steps", 0) for run in runs)
    steps = sum(run.get("scored_steps", 0) for run in runs)
    if not steps:
        return "-"
    low, high = clopper_pearson(covered, steps)
    return f"{100 * covered / steps:.1f} ({100 * low:.1f}-{100 * high:.1f})"


def _difference(stored: dict, wanted: dict) -> str:
    names = sorted(k for k in set(stored) | set(wanted) if stored.get(k) != wanted.get(k))
    return ", ".join(
        f"{k}: {json.dumps(stored.get(k))} there, {json.dumps(wanted.get(k))} now" for k in names
    )


def plot_robustness(runs: list[dict], presets: tuple[str, ...], path: str | Path) -> None:
    """Per preset, each seed's time outside the lane and, where a state network was scored,
    its lateral error beside its MC-dropout spread (the premise of the probabilistic filter:
    the spread grows where the error does)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scored = any("e_y_error_m" in run for run in runs)
    figure, axes = plt.subplots(1, 2 if scored else 1, figsize=(10 if scored else 5, 3.8))
    axes = np.atleast_1d(axes)
    for k, preset in enumerate(presets):
        mine = [run for run in runs if run["look"] == preset]
        outside = [run["time_outside_lane_s"] for run in mine]
        axes[0].scatter(np.full(len(outside), k), outside, color="tab:red", zorder=3)
        if scored:
            errors = [run.get("e_y_error_m", np.nan) for run in mine]
            spreads = [run.get("e_y_spread_m", np.nan) for run in mine]
            axes[1].scatter(np.full(len(mine), k - 0.1), errors, color="tab:blue", zorder=3,
                            label="RMS error" if k == 0 else None)  # fmt: skip
            axes[1].scatter(np.full(len(mine), k + 0.1), spreads, color="tab:orange", zorder=3,
                            label="mean spread" if k == 0 else None)  # fmt: skip
    axes[0].set_ylabel("time outside the lane [s]")
    axes[0].set_title("lane keeping, one dot per seed")
    if scored:
        axes[1].set_ylabel("state network, lateral offset [m]")
        axes[1].set_title("perception: error and MC-dropout spread")
        axes[1].legend()
    for axis in axes:
        axis.set_xticks(range(len(presets)), presets)
        axis.set_xlabel("look (domain-randomisation preset)")
        axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def write_report(runs: list[dict], config: RobustnessConfig, out_dir: str | Path) -> str:
    """``robustness.md``, ``.csv`` and ``.png`` in ``out_dir`` (and, where a state source
    was scored, ``by_track.csv``, whose table ``robustness.md`` holds too); the markdown."""
    out_dir = Path(out_dir)
    rows = robustness_rows(runs, config.presets, config.laps)
    table = markdown_table(TABLE_COLUMNS, rows)
    by_track = track_rows(runs, config.presets)
    if by_track:
        table += "\n\nBy track:\n\n" + markdown_table(TRACK_COLUMNS, by_track)
        write_csv(out_dir / "by_track.csv", TRACK_COLUMNS, by_track)
    if config.faults:
        table = f"With the faults {', '.join(config.faults)}:\n\n{table}"
    (out_dir / "robustness.md").write_text(table + "\n")
    write_csv(out_dir / "robustness.csv", TABLE_COLUMNS, rows)
    plot_robustness(runs, config.presets, out_dir / "robustness.png")
    return table
