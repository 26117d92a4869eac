"""The fault table: every sensor and actuator fault at each severity, each driver, without a
filter and behind the default one (``saferace faults``).

Every fault of :mod:`saferace.faults.spec` starts :data:`FAULT_START_S` into a run (the car
at speed, and time left to see it drive on after a fault that clears), at each severity,
for each driver on each track: once without a filter and once behind the default filter
(the robust CBF fed the generic perception model, or the ``state_source`` named); beside
them the same driver fault-free, which progress is measured against. A row per run is
appended to ``runs.jsonl`` as it ends and a rerun skips the rows there (the same run, on a
track of the same content, for the same seconds and seed), so an interrupted table resumes.

Per run the table (``faults.md``, ``faults.csv``) gives the time outside the lane, whether
the car left the track (which ends a run), its progress against the fault-free run, the
longest standstill while the driver asked to move, how long after a fault that clears the
car was driving again, and the share of steps the filter corrected; ``faults.png`` shows
the time outside, fault by driver, without and behind the filter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from saferace.envs.racing_env import DEFAULT_CONTROL_HZ
from saferace.eval.filters import FilterConfig
from saferace.eval.leaderboard import filter_words, row_filter
from saferace.eval.metrics import thinning_stride
from saferace.eval.parallel import run_jobs
from saferace.eval.runner import append_jsonl, max_steps_for, read_jsonl
from saferace.eval.tables import markdown_table, or_dash, write_csv
from saferace.experiments.fault_table_config import FaultTableConfig
from saferace.experiments.safety_table import RECKLESS_TASKS, Run, table_row
from saferace.faults.spec import parse_fault
from saferace.progress import Progress
from saferace.track.random_track import write_random_tracks
from saferace.track.track import Track

#: When every fault of the table starts (s after the reset).
FAULT_START_S = 3.0
#: Faster than this (m/s) the car drives; the time to drive on is until it does again.
DRIVE_ON_MPS = 1.0
#: Laps a run may drive: more than any drives in its seconds, so that time ends every run.
UNLIMITED_LAPS = 1000


@dataclass(frozen=True)
class FaultRun:
    """One run of the table: a driver on its task and a track, with a ``fault`` (its full
    string, ``""``: none) behind the filter ``safety``."""

    driver: str
    task: str
    track: str
    fault: str
    safety: FilterConfig

    @property
    def key(self) -> tuple:
        return (self.driver, self.task, self.track, self.fault, *self.safety.as_dict().values())


def table_faults(names: list[str], severities: list[int]) -> list[str]:
    """Each fault of ``names`` at each of ``severities``, starting at :data:`FAULT_START_S`,
    as the full string that makes it (every key written out; an unknown name raises
    :class:`~saferace.faults.spec.FaultError`)."""
    return [
        parse_fault(f"{name}:severity={severity},start={FAULT_START_S:g}").spec()
        for name in names
        for severity in severities
    ]


def default_filter(state_source: str, mc_samples: int) -> FilterConfig:
    """The filter every command puts a driver behind by default: the robust CBF over the
    state source's calibrated interval."""
    return FilterConfig(kind="cbf", state_source=state_source, samples=mc_samples)


def planned_fault_runs(
    tracks: list[str], drivers: list[str], faults: list[str], filters: list[FilterConfig]
) -> list[FaultRun]:
    """Every run, in order: per track, driver and filter, fault-free and with each fault; the
    speeding driver on the racing line, every other on the centre line."""
    return [
        FaultRun(driver, RECKLESS_TASKS.get(driver, "CenterLine"), track, fault, safety)
        for track in tracks
        for driver in drivers
        for safety in filters
        for fault in ("", *faults)
    ]


def run_fault_table(
    config: FaultTableConfig,
    out_dir: str | Path,
    workers: int = 1,
    ray_address: str | None = None,
    progress: bool = True,
) -> list[dict]:
    """Run what is not in ``out_dir/runs.jsonl`` yet of the table ``config`` describes (see
    the module; random tracks written to ``out_dir/tracks``) over ``workers`` processes or
    Ray tasks (:func:`~saferace.eval.parallel.run_jobs`); write the table and plot; all
    rows."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tracks = [*config.tracks, *write_random_tracks(out_dir / "tracks", config.random_tracks)]
    specs = table_faults(list(config.faults), list(config.severities))
    filters = [FilterConfig(), default_filter(config.state_source, config.mc_samples)]
    runs = planned_fault_runs(tracks, list(config.drivers), specs, filters)
    made_of = {track: Track.load(track).fingerprint for track in tracks}
    settings = {"seconds": config.seconds, "seed": config.seed}
    runs_file = out_dir / "runs.jsonl"
    done = (
        {tuple(row["resume"]): row for row in read_jsonl(runs_file)} if runs_file.exists() else {}
    )
    keys = {
        run: [*map(str, run.key), made_of[run.track], *map(str, settings.values())] for run in runs
    }
    todo = [run for run in runs if tuple(keys[run]) not in done]

    def keep(job: tuple, row: dict) -> None:
        run = job[0]
        row.update(fault=run.fault, track_arg=run.track, resume=keys[run])
        append_jsonl(runs_file, row)
        done[tuple(keys[run])] = row

    def describe(job: tuple) -> str:
        run = job[0]
        return (
            f"{run.driver} on {Path(run.track).stem}, {run.fault or 'no fault'}, "
            + filter_words(run.safety)
        )

    with Progress(len(todo), "fault table", "run", enabled=progress) as bar:
        run_jobs(
            fault_row,
            [(run, config.seed, max_steps_for(config.seconds)) for run in todo],
            keep,
            workers=workers,
            ray_address=ray_address,
            advance=lambda job: bar.done(describe(job)),
            describe=describe,
        )
    rows = [done[tuple(keys[run])] for run in runs]
    lengths = {track: Track.load(track).length_m for track in tracks}
    lines = table_lines(rows, lengths)
    write_table(lines, out_dir)
    plot_time_outside(lines, out_dir / "faults.png")
    return rows


def fault_row(run: FaultRun, seed: int, max_steps: int | None) -> dict:
    """The result row of one run of the table: the safety table's run of its driver, for
    ``max_steps`` with its fault."""
    faults = {"faults": [run.fault]} if run.fault else {}
    as_table_run = Run(run.driver, run.task, run.track, run.safety)
    return table_row(as_table_run, seed, UNLIMITED_LAPS, {"max_steps": max_steps, **faults})


def distance_m(row: dict, lap_length_m: float) -> float:
    """How far along the track a run drove: its path's arc length, unwrapped over laps."""
    s_m = np.asarray(row["trajectory"]["s_m"], dtype=float)
    if len(s_m) < 2:
        return 0.0
    turns = np.unwrap(s_m * (2.0 * np.pi / lap_length_m))
    return float((turns[-1] - turns[0]) * lap_length_m / (2.0 * np.pi))


def drive_on_s(row: dict, fault: str) -> float | None:
    """How long after ``fault`` cleared the car drove faster than :data:`DRIVE_ON_MPS` (0
    where it never slowed below it; ``inf`` where it never did again); None where the fault
    did not clear before the run ended (it lasts to the end, or the car left the track)."""
    parsed = parse_fault(fault)
    cleared_s = parsed.start_s + parsed.duration_s
    speeds = np.asarray(row["trajectory"]["v_x_mps"], dtype=float)
    stride = thinning_stride(sum(lap["steps"] for lap in row["laps"]))
    times_s = (np.arange(len(speeds)) * stride + 1) / DEFAULT_CONTROL_HZ
    if len(times_s) == 0 or times_s[-1] < cleared_s:
        return None
    driving = np.flatnonzero((times_s >= cleared_s) & (speeds > DRIVE_ON_MPS))
    return math.inf if len(driving) == 0 else max(0.0, float(times_s[driving[0]]) - cleared_s)


#: How the table names a run without faults.
NO_FAULT = "fault-free"
COLUMNS = [
    "track",
    "driver",
    "fault",
    "severity",
    "filter",
    "outside lane [s]",
    "left the track",
    "progress [%]",
    "longest standstill [s]",
    "drives on after [s]",
    "interventions [%]",
]


def table_lines(rows: list[dict], lengths: dict[str, float]) -> list[list]:
    """One table line per run (fault-free ones as :data:`NO_FAULT`, so that the table shows
    what the faults change): its measures, progress against the same driver's fault-free
    run on the same track behind the same filter."""
    free = {
        (row["track_arg"], row["agent"], filter_words_of(row)): row
        for row in rows
        if not row["fault"]
    }
    lines = []
    for row in rows:
        fault, summary = parse_fault(row["fault"]) if row["fault"] else None, row["summary"]
        baseline = free[(row["track_arg"], row["agent"], filter_words_of(row))]
        length = lengths[row["track_arg"]]
        reference = distance_m(baseline, length)
        rate = summary.get("intervention_rate")
        drive_on = drive_on_s(row, row["fault"]) if fault else None
        lines.append(
            [
                row["track"],
                row["agent"],
                NO_FAULT if fault is None else fault.name,
                "-" if fault is None else fault.severity,
                filter_words_of(row),
                summary["time_outside_lane_s"],
                "yes" if row["terminated"] else "no",
                100.0 * distance_m(row, length) / reference if reference > 0.0 else "-",
                or_dash(summary.get("longest_standstill_s")),
                "-" if drive_on is None else "never" if math.isinf(drive_on) else drive_on,
                "-" if rate is None else 100.0 * rate,
            ]
        )
    return lines


def filter_words_of(row: dict) -> str:
    """The filter a row ran behind, in words."""
    return filter_words(row_filter(row))


SUMMARY_COLUMNS = [
    "fault",
    "severity",
    "filter",
    "runs",
    "most outside [s]",
    "left the track",
    "least progress [%]",
    "longest standstill [s]",
    "slowest to drive on [s]",
]


def summary_lines(lines: list[list]) -> list[list]:
    """Per fault, severity and filter, the worst over drivers and tracks: the most time
    outside, the runs that left the track, the least progress, the longest standstill and
    the slowest drive on (``never`` where a car did not)."""
    groups: dict[tuple, list[list]] = {}
    for line in lines:
        groups.setdefault((line[2], line[3], line[4]), []).append(line)
    summary = []
    for (name, severity, safety), group in groups.items():
        progress = [line[7] for line in group if line[7] != "-"]
        standstill = [line[8] for line in group if line[8] != "-"]
        drive_on = [line[9] for line in group if line[9] != "-"]
        slowest = "never" if "never" in drive_on else max(drive_on, default="-")
        summary.append(
            [
                name,
                severity,
                safety,
                len(group),
                max(line[5] for line in group),
                sum(line[6] == "yes" for line in group),
                min(progress, default="-"),
                max(standstill, default="-"),
                slowest,
            ]
        )
    return summary


def write_table(lines: list[list], out_dir: Path) -> None:
    """``faults.md`` (the worst per fault, severity and filter, then every run) and
    ``faults.csv`` (every run)."""
    text = (
        "# Sensor and actuator faults: every driver without and behind the default filter\n\n"
        "## The worst over drivers and tracks\n\n"
        + markdown_table(SUMMARY_COLUMNS, summary_lines(lines))
        + "\n\n## Every run\n\n"
        + markdown_table(COLUMNS, lines)
        + "\n"
    )
    (out_dir / "faults.md").write_text(text)
    write_csv(out_dir / "faults.csv", COLUMNS, lines)


def driver_label(driver: str) -> str:
    """A driver's name on a plot: a checkpoint or module by its file's name alone."""
    kind, _, argument = driver.partition(":")
    return f"{kind}:\n{Path(argument).name}" if argument else driver


def plot_time_outside(lines: list[list], path: Path) -> None:
    """Time outside the lane (summed over tracks, with the runs that left the track), a row
    per fault and severity, a column per driver: a panel per filter."""
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not lines:
        return
    faults = list(dict.fromkeys((line[2], line[3]) for line in lines))
    drivers = list(dict.fromkeys(line[1] for line in lines))
    filters = list(dict.fromkeys(line[4] for line in lines))
    figure, axes = plt.subplots(
        1, len(filters), figsize=(2.0 + 1.3 * len(drivers) * len(filters), 0.35 * len(faults) + 2),
        squeeze=False, layout="constrained",
    )  # fmt: skip
    peak = max(max(float(line[5]) for line in lines), 1e-3)
    for ax, safety in zip(axes[0], filters, strict=True):
        outside = np.zeros((len(faults), len(drivers)))
        left = np.zeros_like(outside, dtype=int)
        for line in lines:
            if line[4] == safety:
                cell = faults.index((line[2], line[3])), drivers.index(line[1])
                outside[cell] += float(line[5])
                left[cell] += line[6] == "yes"
        image = ax.imshow(outside, cmap="Reds", vmin=0.0, vmax=peak, aspect="auto")
        for (i, j), value in np.ndenumerate(outside):
            words = f"{value:.1f}" + (f"\n{left[i, j]} left" if left[i, j] else "")
            shade = "white" if value > 0.6 * peak else "black"  # legible on dark red
            ax.text(j, i, words, ha="center", va="center", fontsize=7, color=shade)
        ax.set_xticks(range(len(drivers)), [driver_label(driver) for driver in drivers])
        ax.set_yticks(
            range(len(faults)),
            [name if name == NO_FAULT else f"{name} {severity}" for name, severity in faults],
        )
        title = "no filter" if safety == filter_words(FilterConfig()) else safety
        ax.set_title(textwrap.fill(title, 28), fontsize=9)
    figure.colorbar(image, ax=axes[0].tolist(), label="time outside the lane [s]")
    figure.savefig(path, dpi=120)
    plt.close(figure)
