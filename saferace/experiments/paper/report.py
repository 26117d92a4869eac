"""The paper's tables in markdown and CSV, with their claims measured below them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from saferace.eval.metrics import longest_standstill
from saferace.eval.tables import markdown_table, write_csv
from saferace.experiments.paper.plots import plot_iterations
from saferace.experiments.paper.presets import (
    PERCEPTION_MODES,
    RUN_KINDS,
    RUN_LABELS,
    Preset,
    TableSetting,
)
from saferace.names import TASKS


def table_lines(
    setting: TableSetting, rows: dict[tuple[str, int, str], list[dict]], seeds: list[int]
) -> list[list]:
    """The paper's layout: a line per iteration and filter, a column group per reference."""
    iterations = max(row["iteration"] for runs in rows.values() for row in runs)
    kinds = [kind for kind, _, _ in RUN_KINDS if any(key[2] == kind for key in rows)]
    lines = []
    for iteration in range(iterations + 1):
        for kind in kinds:
            shown = kind == "none" or any(iteration > setting.filter_from[task] for task in TASKS)
            if not shown:
                continue
            line = [iteration, RUN_LABELS[kind]]
            for task in TASKS:
                own_row = kind == "none" or iteration > setting.filter_from[task]
                found = [
                    row
                    for (t, seed, k), runs in rows.items()
                    if t == task and k == kind and seed in seeds
                    for row in runs
                    if row["iteration"] == iteration
                ]
                line += _cells(found) if own_row and found else ["-"] * len(CELL_NAMES)
            lines.append(line)
    return lines


CELL_NAMES = (
    "lap [s]",
    "mean dev [m]",
    "outside [s]",
    "longest standstill [s]",
    "interventions [%]",
    "held-out dev [m]",
    "held-out outside [s]",
)


def _cells(found: list[dict]) -> list[str]:
    """Cells of one (iteration, filter, line) over seeds: a star marks an unfinished lap
    (its time is how long the car drove), ``a +- b`` the mean and spread over seeds; the
    longest standstill while the driver asked to move is the longest of the seeds' (``-``
    where a row predates it)."""
    completed = [row["completed"] for row in found]
    star = "" if all(completed) else "*"
    if len(found) > 1:
        star = f" ({sum(completed)}/{len(found)} done)" if not all(completed) else ""
    time_driven = [row["lap_time_s"] if row["completed"] else row["duration_s"] for row in found]
    rates = [row["intervention_rate"] for row in found if row["intervention_rate"] is not None]
    return [
        _spread(time_driven) + star,
        _spread([row["mean_abs_deviation_m"] for row in found]) + star,
        _spread([row["time_outside_lane_s"] for row in found]),
        _standstill(found),
        _spread([100.0 * rate for rate in rates]) if rates else "-",
        _spread([row["held_out_mean_abs_deviation_m"] for row in found]),
        _spread([row["held_out_time_outside_lane_s"] for row in found]),
    ]


def _standstill(rows: list[dict]) -> str:
    """The longest standstill of ``rows`` while the driver asked to move, ``-`` where a row
    predates it."""
    longest = longest_standstill(rows)
    return "-" if longest is None else f"{longest:.3g}"


def _spread(values: list[float | None]) -> str:
    """``a`` for one value, ``mean +- std`` for several, ``-`` for none."""
    present = [v for v in values if v is not None]
    if not present:
        return "-"
    if len(present) == 1:
        return f"{present[0]:.3g}"
    return f"{np.mean(present):.3g} +- {np.std(present):.2g}"


def claims(
    setting: TableSetting,
    rows: dict[tuple[str, int, str], list[dict]],
    from_1: dict[tuple[str, int, str], dict],
) -> list[str]:
    """The paper's claims, measured: first completed lap with and without the filter, laps
    completed in the filtered iterations against the unfiltered run's same iterations, lane
    exits and the longest standstill while the driver asked to move in filtered
    iterations, the final lap time against the expert's; and, from
    ``from_1`` (:func:`filtered_from_1`), whether iteration 1 laps behind the filter."""
    lines = []
    order = [kind for kind, _, _ in RUN_KINDS]
    for (task, seed, kind), runs in sorted(rows.items(), key=lambda item: (
        item[0][0], item[0][1], order.index(item[0][2])
    )):  # fmt: skip
        k = setting.filter_from[task]
        own = [row for row in runs if row["iteration"] >= 1 and (kind == "none" or row["filtered"])]
        first = next((row["iteration"] for row in own if row["completed"]), None)
        text = f"- {task}, seed {seed}, {RUN_LABELS[kind]}: first completed lap at iteration "
        text += f"{first}" if first is not None else "none"
        if kind != "none":
            last = runs[-1]["iteration"]
            unfiltered = [row for row in rows[(task, seed, "none")] if k < row["iteration"] <= last]
            exits = [row["iteration"] for row in own if row["time_outside_lane_s"] > 0]
            text += (
                f" (filtered from {k + 1}); laps completed in iterations {k + 1}-"
                f"{runs[-1]['iteration']}: {sum(row['completed'] for row in own)}/{len(own)}, "
                f"without the filter {sum(row['completed'] for row in unfiltered)}/"
                f"{len(unfiltered)}; lane exits in filtered iterations: "
            )
            text += ", ".join(map(str, exits)) if exits else "none"
            text += f"; longest standstill in filtered iterations: {_seconds(own)}"
        final, expert = runs[-1], runs[0]
        if final["completed"] and expert["completed"]:
            ratio = final["lap_time_s"] / expert["lap_time_s"]
            text += (
                f"; final lap {final['lap_time_s']:.2f} s, {100 * (ratio - 1):+.1f}% against the "
                f"expert's {expert['lap_time_s']:.2f} s"
            )
        else:
            text += "; final iteration did not complete its lap"
        lines.append(text)
    for (task, seed, kind), row in sorted(from_1.items()):
        unfiltered_1 = rows[(task, seed, "none")][1]
        lines.append(
            f"- {task}, seed {seed}, iteration 1 behind the filter fed the {RUN_LABELS[kind]} "
            f"state (a fork with k = 0): {_drive(row)}; without the filter {_drive(unfiltered_1)}"
        )
    return lines


VERDICT_COLUMNS = (
    "line",
    "seed",
    "perception",
    "filtered iterations",
    "first lap, filtered run",
    "first lap, unfiltered run",
    "never leaves the lane",
    "longest standstill, filtered [s]",
    "first lap sooner",
)


def verdicts(
    setting: TableSetting,
    rows: dict[tuple[str, int, str], list[dict]],
    from_1: dict[tuple[str, int, str], dict],
) -> list[list]:
    """Whether the paper's two claims hold, per line, seed and perception mode (the paper's
    and the generic model's): the filtered iterations (those after k, and iteration 1 behind
    the filter) never leave the lane (beside it, the longest they stood still while the
    driver asked to move: staying inside by standing still is no success), and the first
    completed lap comes at an earlier iteration with the filter than without: in the
    filtered run (its iterations up to k are the unfiltered run's, driven without the
    filter; iteration 1 counts where it lapped behind the filter) than in the unfiltered
    run."""
    lines = []
    for (task, seed, kind), runs in sorted(rows.items()):
        if kind not in PERCEPTION_MODES:
            continue
        k = setting.filter_from[task]
        filtered = [row for row in runs if row["filtered"]]
        first_row = from_1.get((task, seed, kind))
        if first_row is not None:
            filtered = [first_row, *filtered]
        lapped = [row["iteration"] for row in runs if row["iteration"] >= 1 and row["completed"]]
        if first_row is not None and first_row["completed"]:
            lapped.append(1)
        unfiltered = rows[(task, seed, "none")]
        with_filter = min(lapped, default=None)
        without = next((r["iteration"] for r in unfiltered[1:] if r["completed"]), None)
        exits = [row["iteration"] for row in filtered if row["time_outside_lane_s"] > 0]
        if with_filter is None and without is None:
            sooner = "neither lapped"
        elif without is None or (with_filter is not None and with_filter < without):
            sooner = "holds"
        else:
            sooner = "no (same iteration)" if with_filter == without else "no"
        lines.append(
            [
                task,
                seed,
                RUN_LABELS[kind],
                ", ".join(str(row["iteration"]) for row in filtered) + f" (k = {k})",
                "-" if with_filter is None else with_filter,
                "-" if without is None else without,
                "holds" if not exits else "fails: iteration " + ", ".join(map(str, exits)),
                _standstill(filtered),
                sooner,
            ]
        )
    return lines


def _drive(row: dict) -> str:
    """One drive in words: lapped or not, time outside the lane, longest standstill."""
    done = f"lapped in {row['lap_time_s']:.2f} s" if row["completed"] else "did not lap"
    return (
        f"{done}, {row['time_outside_lane_s']:.2f} s outside the lane, longest standstill "
        + _seconds([row])
    )


def _seconds(rows: list[dict]) -> str:
    """The longest standstill of ``rows`` in words: ``1.20 s``, or ``not recorded``."""
    longest = longest_standstill(rows)
    return "not recorded" if longest is None else f"{longest:.2f} s"


UNSEEN_COLUMNS = (
    "table",
    "line",
    "seed",
    "policy",
    "track",
    "filter",
    "laps",
    "lap [s]",
    "outside [s]",
    "longest standstill [s]",
)


def write_table(
    preset: Preset,
    setting: TableSetting,
    rows: dict[tuple[str, int, str], list[dict]],
    from_1: dict[tuple[str, int, str], dict],
    seeds: list[int],
    out_dir: Path,
) -> list[Path]:
    """``{setting}.md`` with the claims, ``{setting}.csv`` and the trajectory figure."""
    header = ["iteration", "filter"] + [f"{task}: {name}" for task in TASKS for name in CELL_NAMES]
    lines = table_lines(setting, rows, seeds)
    text = (
        f"# {setting.title}\n\npreset {preset.name}, seeds {seeds}; k: "
        + ", ".join(f"{t} {k}" for t, k in setting.filter_from.items())
        + "; * did not complete the lap (its time is how long the car drove)\n\n"
        + markdown_table(header, lines)
        + "\n\n## The paper's claims, by perception mode\n\n"
        + markdown_table(VERDICT_COLUMNS, verdicts(setting, rows, from_1))
        + "\n\n## Claims, measured\n\n"
        + "\n".join(claims(setting, rows, from_1))
        + "\n"
    )
    table_path = out_dir / f"{setting.name}.md"
    table_path.write_text(text)
    csv_path = out_dir / f"{setting.name}.csv"
    write_csv(csv_path, header, lines)
    figure = out_dir / f"{setting.name}_trajectories.png"
    plot_iterations(setting, rows, seeds[0], figure)
    return [table_path, csv_path, figure]


def write_summaries(
    preset: Preset, unseen: list[list], timings: dict[str, float], out_dir: Path
) -> list[Path]:
    """``unseen_tracks.md`` and ``timings.md`` from what has been run so far."""
    unseen_path = out_dir / "unseen_tracks.md"
    unseen_path.write_text(
        f"# Final policies on tracks they never saw (1 lap, at most {preset.max_seconds:g} s)\n\n"
        + markdown_table(UNSEEN_COLUMNS, unseen)
        + "\n"
    )
    timings_path = out_dir / "timings.md"
    timings_path.write_text(
        "# Wall-clock time per stage (s, summed over runs; stages resumed from disk count "
        "as run)\n\n"
        + markdown_table(["stage", "seconds"], [[k, v] for k, v in timings.items()])
        + "\n"
    )
    return [unseen_path, timings_path]
