"""Uncertainty methods side by side under a growing shift (Ovadia et al. 2019).

Each method is one ``saferace robustness`` folder: the same agent, tracks, looks
(``severity-0`` .. ``severity-5``) and seeds, behind the filter fed one state source (MC
dropout, MC dropout with variance scaling, an ensemble, an ensemble with a conformal
calibration, with or without its monitor). :func:`sweep_rows` tabulates per method and
look the interval's coverage (pooled over steps, with its Clopper-Pearson band), its width,
the Gaussian negative log-likelihood, the monitor's alarm rate, time outside the lane, the
lowest barrier, completion, the longest standstill while the driver asked to move and lap
time; :func:`plot_sweep` draws coverage and time outside the lane against the severity, a
line per method.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from saferace.errors import SafeRaceError
from saferace.eval.runner import read_jsonl
from saferace.eval.tables import markdown_table, write_csv
from saferace.experiments.robustness import (
    RUNS_FILE,
    longest_of,
    lowest_of,
    mean_of,
    pooled_coverage,
)

SWEEP_COLUMNS = (
    "method",
    "look",
    "runs",
    "coverage [%] (95% band)",
    "e_y half width [m]",
    "Gaussian NLL",
    "alarms [%]",
    "time outside lane [s]",
    "runs outside",
    "lowest lane barrier [m]",
    "completion [%]",
    "longest standstill [s]",
    "lap time [s]",
)


def load_methods(folders: dict[str, str | Path]) -> dict[str, list[dict]]:
    """Each method's runs from its ``saferace robustness`` folder."""
    methods = {}
    for label, folder in folders.items():
        path = Path(folder) / RUNS_FILE
        if not path.is_file():
            raise SafeRaceError(f"{folder} holds no {RUNS_FILE}: run saferace robustness there")
        methods[label] = read_jsonl(path)
    return methods


def looks_of(methods: dict[str, list[dict]]) -> list[str]:
    """The looks the methods drove, severities in order."""
    looks = {run["look"] for runs in methods.values() for run in runs}
    return sorted(looks, key=lambda look: (_severity(look) is None, _severity(look) or 0, look))


def _severity(look: str) -> int | None:
    prefix, _, level = look.rpartition("-")
    return int(level) if prefix == "severity" and level.isdigit() else None


def sweep_rows(methods: dict[str, list[dict]]) -> list[list]:
    """One row of :data:`SWEEP_COLUMNS` per method and look."""
    rows = []
    for label, runs in methods.items():
        for look in looks_of(methods):
            mine = [run for run in runs if run["look"] == look]
            if not mine:
                continue

            rows.append(
                [
                    label,
                    look,
                    len(mine),
                    pooled_coverage(mine),
                    mean_of(mine, "e_y_half_width_m"),
                    mean_of(mine, "gaussian_nll"),
                    mean_of(mine, "alarm_rate", 100.0),
                    float(sum(run["time_outside_lane_s"] for run in mine)),
                    sum(run["time_outside_lane_s"] > 0 for run in mine),
                    lowest_of(mine, "min_lane_barrier_m"),
                    mean_of(mine, "completion", 100.0),
                    longest_of(mine),
                    mean_of(mine, "lap_time_s"),
                ]
            )
    return rows


def plot_sweep(methods: dict[str, list[dict]], path: str | Path) -> None:
    """Coverage of the interval the filter used and time outside the lane against the
    look, a line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    looks = looks_of(methods)
    figure, (coverage_axis, outside_axis) = plt.subplots(1, 2, figsize=(11, 4.8))
    for label, runs in methods.items():
        coverage, outside = [], []
        for look in looks:
            mine = [run for run in runs if run["look"] == look]
            steps = sum(run.get("scored_steps", 0) for run in mine)
            covered = sum(run.get("covered_steps", 0) for run in mine)
            coverage.append(100.0 * covered / steps if steps else np.nan)
            outside.append(sum(run["time_outside_lane_s"] for run in mine) if mine else np.nan)
        coverage_axis.plot(range(len(looks)), coverage, "o-", label=label)
        outside_axis.plot(range(len(looks)), outside, "o-", label=label)
    coverage_axis.axhline(95.0, color="0.4", ls="--", lw=1, label="nominal 95%")
    coverage_axis.set_ylabel("steps with the truth inside the interval [%]")
    coverage_axis.set_title("coverage of the interval the filter used")
    outside_axis.set_ylabel("time outside the lane, all runs [s]")
    outside_axis.set_title("lane keeping")
    for axis in (coverage_axis, outside_axis):
        axis.set_xticks(range(len(looks)), looks, rotation=20)
        axis.set_xlabel("look (shift severity)")
        axis.grid(alpha=0.3)
    handles, labels = coverage_axis.get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", ncol=4, fontsize=8, frameon=False)
    figure.tight_layout(rect=(0.0, 0.12, 1.0, 1.0))  # room for the legend, off the lines
    figure.savefig(path, dpi=120)
    plt.close(figure)


def write_sweep_report(folders: dict[str, str | Path], out_dir: str | Path) -> str:
    """``shift_sweep.md``, ``.csv`` and ``.png`` in ``out_dir``; the markdown table."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    methods = load_methods(folders)
    rows = sweep_rows(methods)
    table = markdown_table(SWEEP_COLUMNS, rows)
    (out_dir / "shift_sweep.md").write_text(table + "\n")
    write_csv(out_dir / "shift_sweep.csv", SWEEP_COLUMNS, rows)
    plot_sweep(methods, out_dir / "shift_sweep.png")
    return table
