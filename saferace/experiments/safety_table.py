"""What the safety filter does: reckless agents and the expert, with and without it.

One command (``saferace safety-table``) runs, on every given track: each reckless agent
without a filter, with the oracle filter, and with noisy state samples through the
probabilistic filter and through the deterministic filter on the samples' mean; and the
MPC expert on both tasks without and with the oracle filter (its lap-time cost), with the
filter's gains named by ``gains`` (the paper's or the tuned ones). Rows are
appended to ``runs.jsonl`` as each run ends and a rerun skips the runs already there (the
same run, on a track of the same content, at the same laps, seed and step limit), so an
interrupted table resumes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

from saferace.errors import ConfigError
from saferace.eval.filters import FilterConfig
from saferace.eval.leaderboard import (
    filter_phrase,
    filter_words,
    row_filter,
    state_source_words,
)
from saferace.eval.parallel import run_jobs
from saferace.eval.runner import (
    append_jsonl,
    evaluate,
    max_steps_for,
    read_jsonl,
    standstill_words,
)
from saferace.eval.tables import markdown_table, or_dash, write_csv
from saferace.experiments.filter_comparison import plot_failures, write_comparison
from saferace.faults.spec import canonical_faults
from saferace.learning.checkpoint import is_calibrated
from saferace.names import AUTO, DEFAULT_GAINS, ROBUST_GAINS, SQUARED_SLACK, TASKS
from saferace.names import RANDOM_TRACK_RADIUS_M as RANDOM_TRACK_RADIUS_M  # size of test tracks
from saferace.progress import Progress
from saferace.track.random_track import write_random_tracks
from saferace.track.track import Track

LOG = logging.getLogger(__name__)

RECKLESS_TASKS = {"drift": "CenterLine", "weave": "CenterLine", "speeding": "RacingLine"}
#: What each name of :data:`~saferace.names.COMPARED_FILTERS` runs: family and slack penalty.
FILTER_SETTINGS = {
    "cbf": ("cbf", SQUARED_SLACK),
    "cbf-l1": ("cbf", "l1"),
    "mpsf": ("mpsf", SQUARED_SLACK),
}


@dataclass(frozen=True)
class Run:
    """One table entry: an agent on a task and track behind a filter configuration."""

    agent: str
    task: str
    track: str
    safety: FilterConfig

    @property
    def key(self) -> tuple:
        return run_key(self.agent, self.task, self.track, self.safety)


def planned_runs(
    tracks: list[str],
    noise: tuple[float, float],
    samples: int,
    model: str,
    gains: str,
    state_source: str | None = None,
    mc_samples: int = 10,
    robust: bool = True,
    filters: tuple[str, ...] = ("cbf",),
) -> list[Run]:
    """Every run of the table, in order: per track, each reckless agent without a filter and
    behind each of ``filters`` (:data:`FILTER_SETTINGS`) on the true state, on noisy state
    with chance constraints (the predictive filter: its lane tightened by the samples'
    interval) and on the samples' mean; the expert without and behind each filter on the
    true state. ``state_source`` (``generic[:RECIPE]`` or ``learned:CHECKPOINT``) adds the
    reckless agents behind
    each filter fed that source: with ``robust`` (its checkpoint is calibrated) in the
    robust mode over its conformal interval (what ``auto`` gives a learned source), and
    with ``gains`` through the paper's chance constraints and on the samples' mean."""
    reckless_filters, expert_filters = [FilterConfig()], [FilterConfig()]
    for name in filters:
        kind, slack = FILTER_SETTINGS[name]
        oracle = FilterConfig(kind=kind, model=model, gains=gains, slack=slack)
        noisy = replace(oracle, state_noise=noise, samples=samples)
        reckless_filters += [oracle, noisy, replace(noisy, probabilistic=False)]
        if state_source is not None:
            learned = replace(oracle, state_source=state_source, samples=mc_samples)
            calibrated = FilterConfig(
                kind=kind, model=model, state_source=state_source, samples=mc_samples, slack=slack
            )
            reckless_filters += [calibrated] if robust else []
            reckless_filters += [learned, replace(learned, probabilistic=False)]
        expert_filters.append(oracle)
    runs = []
    for track in tracks:
        for agent, task in RECKLESS_TASKS.items():
            for safety in reckless_filters:
                runs.append(Run(agent, task, track, safety))
        for task in TASKS:
            for safety in expert_filters:
                runs.append(Run("expert", task, track, safety))
    return runs


def run_table(
    tracks: list[str],
    out_dir: str | Path,
    laps: int = 3,
    max_seconds: float = 60.0,
    noise: tuple[float, float] = (0.05, 0.05),
    samples: int = 20,
    model: str = AUTO,
    gains: str = DEFAULT_GAINS,
    seed: int = 0,
    progress: bool = True,
    state_source: str | None = None,
    mc_samples: int = 10,
    workers: int = 1,
    ray_address: str | None = None,
    random_tracks: tuple[int, ...] = (),
    filters: tuple[str, ...] = ("cbf",),
    faults: tuple[str, ...] = (),
) -> list[dict]:
    """Run what is not in ``out_dir/runs.jsonl`` yet (over ``workers`` processes or Ray
    tasks, see :func:`~saferace.eval.parallel.run_jobs`) on ``tracks`` and a random track
    per seed of ``random_tracks`` (written to ``out_dir/tracks``) behind each of
    ``filters``, every run with the sensor ``faults`` (:mod:`saferace.faults`); write the
    tables, the filters' comparison and the plots; all rows."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tracks = [*tracks, *write_random_tracks(out_dir / "tracks", random_tracks)]
    env_kwargs = {
        "max_steps": max_steps_for(max_seconds),
        **({"faults": list(canonical_faults(faults))} if faults else {}),
    }
    made_of = {track: Track.load(track).fingerprint for track in tracks}
    settings = {"laps": laps, "seed": seed, **env_kwargs}
    runs_file = out_dir / "runs.jsonl"
    done = {_row_key(row): row for row in read_jsonl(runs_file)} if runs_file.exists() else {}
    kind, _, checkpoint = (state_source or "").partition(":")
    robust = kind != "learned" or is_calibrated(checkpoint)
    if not robust:
        LOG.warning(
            "%s has no conformal calibration: the table leaves out its robust rows "
            "(saferace calibrate CKPT DATA --out CKPT2 makes one)",
            state_source,
        )
    unknown = sorted(set(filters) - set(FILTER_SETTINGS))
    if unknown or not filters:
        raise ConfigError("filters", f"name some of {', '.join(FILTER_SETTINGS)}, got {unknown}")
    runs = planned_runs(
        tracks, noise, samples, model, gains, state_source, mc_samples, robust, filters
    )
    keys = {run: resume_key(run.key, made_of[run.track], settings) for run in runs}
    todo = [run for run in runs if keys[run] not in done]

    def keep(job: tuple, row: dict) -> None:
        row["resume"] = {"track_fingerprint": made_of[job[0].track], **settings}
        append_jsonl(runs_file, row)
        done[keys[job[0]]] = row

    def describe(job: tuple) -> str:
        return " ".join(map(str, job[0].key[:4]))

    def finished_words(job: tuple) -> str:
        row = done.get(keys[job[0]])
        return "failed" if row is None else row_words(row)

    with Progress(len(todo), "safety table", "run", enabled=progress) as bar:
        run_jobs(
            table_row,
            [(run, seed, laps, env_kwargs) for run in todo],
            keep,
            workers=workers,
            ray_address=ray_address,
            advance=lambda job: bar.done(describe(job), finished_words(job)),
            describe=describe,
        )
    rows = [done[keys[run]] for run in runs]
    write_tables(rows, out_dir, gains, filters)
    write_comparison(rows, out_dir, laps)
    plot_reckless_paths(rows, out_dir / "reckless_paths.png")
    plot_failures(rows, out_dir / "failures", laps)
    return rows


def table_row(run: Run, seed: int, laps: int, env_kwargs: dict) -> dict:
    """The result row of one run of the table."""
    (row,) = evaluate(
        run.agent,
        run.task,
        run.track,
        [seed],
        laps=laps,
        progress=False,
        env_kwargs=env_kwargs,
        safety=run.safety,
    )
    row["track_arg"] = run.track
    return row


def row_words(row: dict) -> str:
    """A run's key numbers, as its progress line says them."""
    summary = row["summary"]
    words = (
        f"{summary['laps_completed']} laps, {summary['time_outside_lane_s']:.2f} s outside, "
        + standstill_words(summary.get("longest_standstill_s"))
    )
    rate = summary.get("intervention_rate")
    return words if rate is None else f"{words}, {100.0 * rate:.0f}% of steps corrected"


def run_key(agent: str, task: str, track: str, safety: FilterConfig) -> tuple:
    """What makes a run of the table: a rerun skips the runs whose key it finds."""
    return (agent, task, track, safety.label, safety.gains, safety.state_source, safety.samples)


def resume_key(key: tuple, track_fingerprint: str, settings: dict) -> tuple:
    """What a rerun matches a kept row by: the run's :func:`run_key`, its track's content
    (a CSV edited under the same name is a new track) and the table's laps, seed and step
    limit and faults (a rerun with ``--laps 3`` into a folder of 1-lap rows kept those)."""
    hashable = {name: tuple(v) if isinstance(v, list) else v for name, v in settings.items()}
    return (*key, track_fingerprint, *sorted(hashable.items()))


def _row_key(row: dict) -> tuple:
    resume = dict(row.get("resume", {}))
    fingerprint = resume.pop("track_fingerprint", None)
    key = run_key(row["agent"], row["task"], row["track_arg"], row_filter(row))
    return resume_key(key, str(fingerprint), resume)


def filter_label(row: dict) -> str:
    """The :attr:`FilterConfig.label` of a result row."""
    return row_filter(row).label


TABLE_COLUMNS = [
    "track",
    "agent",
    "task",
    "filter",
    "state source",
    "laps",
    "outside lane [s]",
    "longest standstill [s]",
    "min barrier [m]",
    "interventions [%]",
    "failed solves",
    "max slack",
    "mean lap [s]",
    "solve median/p95 [ms]",
]


def table_rows(rows: list[dict]) -> list[list]:
    """One table line per run; its longest standstill while the driver asked to move is
    ``-`` in a row written before it was recorded."""
    lines = []
    for row in rows:
        summary = row["summary"]
        rate = summary.get("intervention_rate")
        solver = row.get("filter_solver")
        config = row_filter(row)
        lines.append(
            [
                row["track"],
                row["agent"],
                row["task"],
                filter_words(config),
                state_source_words(config),
                summary["laps_completed"],
                summary["time_outside_lane_s"],
                or_dash(summary.get("longest_standstill_s")),
                summary["min_lane_barrier_m"],
                "-" if rate is None else 100.0 * rate,
                summary.get("failed_solves", "-"),
                summary.get("max_slack", "-"),
                summary["mean_lap_time_s"] if summary["mean_lap_time_s"] is not None else "-",
                f"{solver['solve_median_ms']:.3f}/{solver['solve_p95_ms']:.3f}" if solver else "-",
            ]
        )
    return lines


def expert_cost_rows(rows: list[dict]) -> list[list]:
    """Per track, task and filter: the expert's mean lap time without and with the filter
    on the true state, and the filtered run's laps, time outside the lane and longest
    standstill while the expert asked to move (``-`` where not recorded)."""
    by_key = {(r["track"], r["task"], filter_label(r)): r for r in rows}
    lines = []
    for (track, task, _), row in by_key.items():
        safety = row_filter(row)
        oracle = safety.kind != "none" and not safety.uncertain_state
        if row["agent"] != "expert" or not oracle or (track, task, "none") not in by_key:
            continue
        free = by_key[(track, task, "none")]["summary"]["mean_lap_time_s"]
        filtered = row["summary"]["mean_lap_time_s"]
        cost = 100.0 * (filtered / free - 1.0) if free and filtered else None
        lines.append(
            [
                track,
                task,
                filter_words(safety),
                "-" if free is None else free,
                "-" if filtered is None else filtered,
                "-" if cost is None else cost,
                100.0 * row["summary"]["intervention_rate"],
                row["summary"]["laps_completed"],
                row["summary"]["time_outside_lane_s"],
                or_dash(row["summary"].get("longest_standstill_s")),
            ]
        )
    return lines


EXPERT_COLUMNS = [
    "track",
    "task",
    "filter",
    "lap, no filter [s]",
    "lap, filter [s]",
    "lap-time cost [%]",
    "interventions [%]",
    "laps",
    "outside lane [s]",
    "longest standstill [s]",
]


def write_tables(
    rows: list[dict], out_dir: Path, gains: str, filters: tuple[str, ...] = ("cbf",)
) -> None:
    """``safety_table.md`` (both tables) and ``safety_table.csv`` / ``expert_cost.csv``."""
    runs, costs = table_rows(rows), expert_cost_rows(rows)
    text = (
        f"# Safety filters {', '.join(filters)} (CBF: {gains} gains, robust rows "
        f"{ROBUST_GAINS}): reckless agents and the expert\n\n"
        + markdown_table(TABLE_COLUMNS, runs)
        + "\n\n## Expert lap-time cost of the filter\n\n"
        + markdown_table(EXPERT_COLUMNS, costs)
        + "\n"
    )
    (out_dir / "safety_table.md").write_text(text)
    for name, columns, lines in (
        ("safety_table.csv", TABLE_COLUMNS, runs),
        ("expert_cost.csv", EXPERT_COLUMNS, costs),
    ):
        write_csv(out_dir / name, columns, lines)


#: A colour per :attr:`FilterConfig.label`; other settings take the colour cycle's next.
FILTER_COLOURS = {
    "none": "black",
    "oracle": "tab:green",
    "noisy-prob": "tab:blue",
    "noisy-det": "tab:orange",
    "learned-prob": "tab:purple",
    "learned-det": "tab:brown",
    "learned-robust": "tab:red",
}
#: Inches per metre of a circuit on ``reckless_paths.png``, and the size of a panel's
#: longer side (inches) that a small track is drawn at and a long circuit is capped at.
INCHES_PER_M, PANEL_MIN_IN, PANEL_MAX_IN = 1 / 15, 3.6, 9.0
#: The picture's largest side in pixels: a big grid of long circuits gets a lower dpi.
MAX_PIXELS, MAX_DPI = 4800, 150


def panel_inches(track) -> tuple[float, float]:
    """A track's panel size (width, height) in inches: its bounding box's aspect, the
    longer side growing with the circuit from :data:`PANEL_MIN_IN` to :data:`PANEL_MAX_IN`,
    so that the lane of a 400 m circuit stays visible."""
    import numpy as np

    left, right = track.boundaries()
    points = np.vstack([left, right])
    width_m, height_m = points.max(axis=0) - points.min(axis=0)
    longer = float(np.clip(max(width_m, height_m) * INCHES_PER_M, PANEL_MIN_IN, PANEL_MAX_IN))
    scale = longer / max(width_m, height_m)
    # very thin tracks still get room for the title
    return max(width_m * scale, 0.4 * longer), max(height_m * scale, 0.4 * longer)


def plot_reckless_paths(rows: list[dict], path: Path) -> None:
    """The reckless agents' paths on each track, one colour per filter setting, the
    legend above the panels; a panel is as large as its circuit needs (:func:`panel_inches`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from saferace.eval.runner import row_track, track_key
    from saferace.eval.track_plots import plot_path, plot_track

    reckless = [row for row in rows if row["agent"] in RECKLESS_TASKS]
    keys = list(dict.fromkeys(track_key(row) for row in reckless))
    agents = list(RECKLESS_TASKS)
    if not keys:
        return
    tracks = {}
    for key in keys:
        index, first = next((i, r) for i, r in enumerate(reckless) if track_key(r) == key)
        where = f"reckless row {index + 1} ({first['agent']} on {first['track']})"
        tracks[key] = row_track(first, where)
    sizes = [panel_inches(track) for track in tracks.values()]
    width = max(w for w, _ in sizes) * len(agents)
    heights = [h + 0.5 for _, h in sizes]  # each panel's title
    legend_in = 0.3 * (1 + len({filter_label(row) for row in reckless}))
    figure, axes = plt.subplots(
        len(keys), len(agents), figsize=(width, sum(heights) + legend_in), squeeze=False,
        gridspec_kw={"height_ratios": heights}, layout="constrained",
    )  # fmt: skip
    colours: dict[str, str] = {}
    for i, (key, track) in enumerate(tracks.items()):
        for j, agent in enumerate(agents):
            ax = axes[i, j]
            plot_track(ax, track)
            for row in reckless:
                if track_key(row) != key or row["agent"] != agent:
                    continue
                config = row_filter(row)
                colour = FILTER_COLOURS.get(config.label) or colours.setdefault(
                    config.label, f"C{len(colours) + 5}"
                )
                label = filter_phrase(config)
                plot_path(ax, row["trajectory"], color=colour, lw=1.0, label=label)
            ax.set_title(f"{agent} on {track.name} (x: outside the lane)")
            ax.set_aspect("equal")
            ax.set_axis_off()
    handles, labels = {}, []
    for ax in axes.flat:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            if label not in handles and label != "start/finish":
                handles[label] = handle
                labels.append(label)
    figure.legend(
        [handles[label] for label in labels], labels, loc="outside upper center",
        ncol=min(len(labels), 2), frameon=False,
    )  # fmt: skip
    dpi = min(MAX_DPI, MAX_PIXELS / max(figure.get_size_inches()))
    figure.savefig(path, dpi=dpi)
    plt.close(figure)
