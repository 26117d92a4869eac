"""The filters of one safety table side by side, and a picture of each track where one failed.

``saferace safety-table --filters cbf cbf-l1 mpsf`` drives the same agents on the same
tracks behind each filter; this module sums its rows up per filter, agent and state
source (``filter_comparison.md`` and ``.csv``) and draws, per track where a filtered run
left the lane or did not finish, the paths of those runs (``failures/TRACK.png``).
"""

from __future__ import annotations

import re
from collections import defaultdict
from pathlib import Path

import numpy as np

from saferace.eval.leaderboard import filter_phrase, filter_words, row_filter, state_source_words
from saferace.eval.metrics import STOP_SPEED_MPS, longest_standstill
from saferace.eval.tables import markdown_table, or_dash, write_csv

COMPARISON_COLUMNS = [
    "filter",
    "agent",
    "state source",
    "runs",
    "completed",
    "runs outside lane",
    "outside lane [s]",
    "longest stop [s]",
    "longest standstill [s]",
    "lap-time cost to the expert [%]",
    "interventions [%]",
    "solve median [ms]",
    "step median [ms]",
]


def failed(row: dict, laps: int) -> bool:
    """Whether a run left its lane or did not finish its laps."""
    summary = row["summary"]
    return summary["time_outside_lane_s"] > 0.0 or summary["laps_completed"] < laps


def comparison_rows(rows: list[dict], laps: int) -> list[list]:
    """One line per filter, agent and state source over every track: runs, runs that
    finished their ``laps``, runs that left the lane and their time outside, the longest the
    car stood still within a lap of any of them (a deadlocked filter holds it for seconds;
    "-" where a row predates the metric) and the longest it stood still while the driver
    asked to move (likewise), the expert's mean lap-time cost to its unfiltered
    run on the same track and task, the filter's interventions and its median solve and
    whole-step times (the median of the runs')."""
    free = {
        (row["track"], row["task"]): row["summary"]["mean_lap_time_s"]
        for row in rows
        if row["agent"] == "expert" and row_filter(row).kind == "none"
    }
    groups: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for row in rows:
        config = row_filter(row)
        groups[(filter_words(config), row["agent"], state_source_words(config))].append(row)
    lines = []
    for (words, agent, source), group in groups.items():
        summaries = [row["summary"] for row in group]
        costs = [
            100.0 * (summary["mean_lap_time_s"] / free[(row["track"], row["task"])] - 1.0)
            for row, summary in zip(group, summaries, strict=True)
            if agent == "expert"
            and words != "none"
            and summary["mean_lap_time_s"]
            and free.get((row["track"], row["task"]))
        ]
        stops = [s["longest_stop_s"] for s in summaries if s.get("longest_stop_s") is not None]
        rates = [
            s["intervention_rate"] for s in summaries if s.get("intervention_rate") is not None
        ]
        solves = [
            row["filter_solver"]["solve_median_ms"] for row in group if row.get("filter_solver")
        ]
        steps = [
            row["filter_solver"]["step_median_ms"]
            for row in group
            if "step_median_ms" in row.get("filter_solver", {})
        ]
        lines.append(
            [
                words,
                agent,
                source,
                len(group),
                sum(s["laps_completed"] >= laps for s in summaries),
                sum(s["time_outside_lane_s"] > 0.0 for s in summaries),
                sum(s["time_outside_lane_s"] for s in summaries),
                max(stops) if len(stops) == len(summaries) else "-",  # rows predating it
                or_dash(longest_standstill(summaries)),
                float(np.mean(costs)) if costs else "-",
                100.0 * float(np.mean(rates)) if rates else "-",
                float(np.median(solves)) if solves else "-",
                float(np.median(steps)) if steps else "-",
            ]
        )
    return lines


def write_comparison(rows: list[dict], out_dir: Path, laps: int) -> None:
    """``filter_comparison.md`` and ``.csv`` in ``out_dir``."""
    lines = comparison_rows(rows, laps)
    tracks = list(dict.fromkeys(row["track"] for row in rows))
    (out_dir / "filter_comparison.md").write_text(
        f"# Filters compared on {len(tracks)} tracks ({', '.join(tracks)}), {laps} lap(s)\n\n"
        "Completed: runs that finished their laps. Longest stop: the longest the car stood "
        f"still (forward speed below {STOP_SPEED_MPS} m/s) within a lap of any run. Longest "
        "standstill: the same, counting only the steps in which the driver asked to move "
        "(its own acceleration command, before the filter, was positive): a filter that "
        "keeps a car in its lane by holding it still shows here. Lap-time cost: the expert's "
        "mean over the tracks and tasks, against its unfiltered lap.\n\n"
        + markdown_table(COMPARISON_COLUMNS, lines)
        + "\n"
    )
    write_csv(out_dir / "filter_comparison.csv", COMPARISON_COLUMNS, lines)


def plot_failures(rows: list[dict], out_dir: Path, laps: int) -> list[Path]:
    """Per track where a filtered run failed (:func:`failed`), its track with those runs'
    paths, one colour per run; the pictures' paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from saferace.eval.runner import row_track, track_key
    from saferace.eval.track_plots import plot_path, plot_track

    by_track: dict[tuple, list[dict]] = defaultdict(list)
    for row in rows:
        if row_filter(row).kind != "none" and failed(row, laps):
            by_track[track_key(row)].append(row)
    written = []
    for failures in by_track.values():
        track = row_track(failures[0], f"{failures[0]['agent']} on {failures[0]['track']}")
        figure, ax = plt.subplots(figsize=(9, 9), layout="constrained")
        plot_track(ax, track)
        for index, row in enumerate(failures):
            summary = row["summary"]
            label = (
                f"{row['agent']} / {row['task']}, {filter_phrase(row_filter(row))}: "
                f"{summary['time_outside_lane_s']:.2f} s outside, "
                f"{summary['laps_completed']}/{laps} laps"
            )
            plot_path(ax, row["trajectory"], color=f"C{index}", lw=1.0, label=label)
        ax.set_title(f"Filtered runs that failed on {track.name} (x: outside the lane)")
        ax.set_aspect("equal")
        ax.set_axis_off()
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.02), fontsize=7, frameon=False)
        out_dir.mkdir(parents=True, exist_ok=True)
        path = out_dir / f"{re.sub(r'[^A-Za-z0-9_.-]+', '_', track.name)}.png"
        figure.savefig(path, dpi=110, bbox_inches="tight")
        plt.close(figure)
        written.append(path)
    return written
