"""What the safety filter does: reckless agents and the expert, with and without it.

One command (``saferace safety-table``) runs, on every given track: each reckless agent
without a filter, with the oracle filter, and with noisy state samples through the
probabilistic filter and through the deterministic filter on the samples' mean; and the
MPC expert on both tasks without and with the oracle filter (its lap-time cost), with the
filter's gains named by ``gains`` (the paper's or the tuned ones). Rows are
appended to ``runs.jsonl`` as each run ends and a rerun skips the runs already there, so
an interrupted table resumes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from tqdm import tqdm

from saferace.eval.filters import FilterConfig
from saferace.eval.parallel import run_jobs
from saferace.eval.runner import append_jsonl, evaluate, max_steps_for, read_jsonl
from saferace.eval.tables import markdown_table, write_csv
from saferace.names import DEFAULT_GAINS, TASKS
from saferace.track.random_track import write_random_tracks

RECKLESS_TASKS = {"drift": "CenterLine", "weave": "CenterLine", "speeding": "RacingLine"}
#: Size of generated test tracks: tight enough that 1.6x the racing line's speed exceeds
#: the grip within a lap (on gentle tracks the car's 7 m/s top speed caps the agent).


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
) -> list[Run]:
    """Every run of the table, in order; ``state_source`` (``learned:CHECKPOINT``) adds the
    reckless agents through the filter fed that source's samples, probabilistic and not."""
    oracle = FilterConfig(kind="cbf", model=model, gains=gains)
    noisy = FilterConfig(kind="cbf", model=model, state_noise=noise, samples=samples, gains=gains)
    reckless_filters = [FilterConfig(), oracle, noisy, replace(noisy, probabilistic=False)]
    if state_source is not None:
        learned = replace(oracle, state_source=state_source, samples=mc_samples)
        reckless_filters += [learned, replace(learned, probabilistic=False)]
    runs = []
    for track in tracks:
        for agent, task in RECKLESS_TASKS.items():
            for safety in reckless_filters:
                runs.append(Run(agent, task, track, safety))
        for task in TASKS:
            for safety in (FilterConfig(), oracle):
                runs.append(Run("expert", task, track, safety))
    return runs


def run_table(
    tracks: list[str],
    out_dir: str | Path,
    laps: int = 3,
    max_seconds: float = 60.0,
    noise: tuple[float, float] = (0.05, 0.05),
    samples: int = 20,
    model: str = "kinematic",
    gains: str = DEFAULT_GAINS,
    seed: int = 0,
    progress: bool = True,
    state_source: str | None = None,
    mc_samples: int = 10,
    workers: int = 1,
    ray_address: str | None = None,
    random_tracks: tuple[int, ...] = (),
) -> list[dict]:
    """Run what is not in ``out_dir/runs.jsonl`` yet (over ``workers`` processes or Ray
    tasks, see :func:`~saferace.eval.parallel.run_jobs`) on ``tracks`` and a random track
    per seed of ``random_tracks`` (written to ``out_dir/tracks``); write the tables; all
    rows."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tracks = [*tracks, *write_random_tracks(out_dir / "tracks", random_tracks)]
    runs_file = out_dir / "runs.jsonl"
    done = {_row_key(row): row for row in read_jsonl(runs_file)} if runs_file.exists() else {}
    runs = planned_runs(tracks, noise, samples, model, gains, state_source, mc_samples)
    todo = [run for run in runs if run.key not in done]
    env_kwargs = {"max_steps": max_steps_for(max_seconds)}

    def keep(job: tuple, row: dict) -> None:
        append_jsonl(runs_file, row)
        done[job[0].key] = row

    with tqdm(
        total=len(todo), desc="safety table", unit="run", disable=None if progress else True
    ) as bar:
        run_jobs(
            table_row,
            [(run, seed, laps, env_kwargs) for run in todo],
            keep,
            workers=workers,
            ray_address=ray_address,
            advance=bar.update,
            describe=lambda job: " ".join(map(str, job[0].key[:4])),
        )
    rows = [done[run.key] for run in runs]
    write_tables(rows, out_dir, gains)
    plot_reckless_paths(rows, out_dir / "reckless_paths.png")
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


def run_key(agent: str, task: str, track: str, safety: FilterConfig) -> tuple:
    """What makes a run of the table: a rerun skips the runs whose key it finds."""
    return (agent, task, track, safety.label, safety.gains, safety.state_source, safety.samples)


def _row_key(row: dict) -> tuple:
    return run_key(row["agent"], row["task"], row["track_arg"], row_filter(row))


def row_filter(row: dict) -> FilterConfig:
    """The :class:`FilterConfig` of a result row."""
    config = dict(row["filter"])
    if config.get("state_noise") is not None:
        config["state_noise"] = tuple(config["state_noise"])
    return FilterConfig(**config)


def filter_label(row: dict) -> str:
    """The :attr:`FilterConfig.label` of a result row."""
    return row_filter(row).label


TABLE_COLUMNS = [
    "track",
    "agent",
    "task",
    "filter",
    "laps",
    "outside lane [s]",
    "min barrier [m]",
    "interventions [%]",
    "failed solves",
    "max slack",
    "mean lap [s]",
    "solve median/p95 [ms]",
]


def table_rows(rows: list[dict]) -> list[list]:
    """One table line per run."""
    lines = []
    for row in rows:
        summary = row["summary"]
        rate = summary.get("intervention_rate")
        solver = row.get("filter_solver")
        lines.append(
            [
                row["track"],
                row["agent"],
                row["task"],
                filter_label(row),
                summary["laps_completed"],
                summary["time_outside_lane_s"],
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
    """Per track and task: the expert's mean lap time without and with the oracle filter."""
    by_key = {(r["track"], r["task"], filter_label(r)): r for r in rows}
    lines = []
    for (track, task, label), row in by_key.items():
        if row["agent"] != "expert" or label != "oracle" or (track, task, "none") not in by_key:
            continue
        free = by_key[(track, task, "none")]["summary"]["mean_lap_time_s"]
        filtered = row["summary"]["mean_lap_time_s"]
        cost = 100.0 * (filtered / free - 1.0) if free and filtered else None
        lines.append(
            [
                track,
                task,
                "-" if free is None else free,
                "-" if filtered is None else filtered,
                "-" if cost is None else cost,
                100.0 * row["summary"]["intervention_rate"],
                row["summary"]["time_outside_lane_s"],
            ]
        )
    return lines


EXPERT_COLUMNS = [
    "track",
    "task",
    "lap, no filter [s]",
    "lap, filter [s]",
    "lap-time cost [%]",
    "interventions [%]",
    "outside lane [s]",
]


def write_tables(rows: list[dict], out_dir: Path, gains: str) -> None:
    """``safety_table.md`` (both tables) and ``safety_table.csv`` / ``expert_cost.csv``."""
    runs, costs = table_rows(rows), expert_cost_rows(rows)
    text = (
        f"# Safety filter ({gains} gains): reckless agents and the expert\n\n"
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


FILTER_STYLES = {
    "none": ("black", "no filter"),
    "oracle": ("tab:green", "filter, true state"),
    "noisy-prob": ("tab:blue", "probabilistic filter, noisy state"),
    "noisy-det": ("tab:orange", "deterministic filter, noisy mean"),
    "learned-prob": ("tab:purple", "probabilistic filter, perceived state"),
    "learned-det": ("tab:brown", "deterministic filter, perceived mean"),
}


def plot_reckless_paths(rows: list[dict], path: Path) -> None:
    """The reckless agents' paths on each track, one colour per filter setting."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from saferace.eval.track_plots import plot_path, plot_track
    from saferace.track import Track

    reckless = [row for row in rows if row["agent"] in RECKLESS_TASKS]
    tracks = list(dict.fromkeys(row["track_arg"] for row in reckless))
    agents = list(RECKLESS_TASKS)
    if not tracks:
        return
    figure, axes = plt.subplots(
        len(tracks), len(agents), figsize=(4 * len(agents), 3.6 * len(tracks)), squeeze=False
    )
    for i, track_arg in enumerate(tracks):
        track = Track.load(track_arg)
        for j, agent in enumerate(agents):
            ax = axes[i, j]
            plot_track(ax, track)
            for row in reckless:
                if row["track_arg"] != track_arg or row["agent"] != agent:
                    continue
                colour, label = FILTER_STYLES[filter_label(row)]
                plot_path(ax, row["trajectory"], color=colour, lw=1.0, label=label)
            ax.set_title(f"{agent} on {track.name} (x: outside the lane)")
            ax.set_aspect("equal")
            ax.set_axis_off()
    handles, labels = axes[0, 0].get_legend_handles_labels()
    columns = min(len(labels), 3)
    figure.legend(handles, labels, loc="upper center", ncol=columns)
    legend_rows = -(-len(labels) // columns)
    figure.tight_layout(rect=(0, 0, 1, 1.0 - 0.04 * legend_rows / len(tracks)))
    figure.savefig(path, dpi=90)
    plt.close(figure)
