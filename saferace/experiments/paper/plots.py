"""The paper's trajectory figures (Figs. 5-9): every iteration's path over the track."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from saferace.eval.track_plots import plot_path, plot_track, plt
from saferace.experiments.paper.presets import RUN_KINDS, RUN_LABELS, TableSetting
from saferace.names import TASKS
from saferace.track import Track


def plot_iterations(
    setting: TableSetting, rows: dict[tuple[str, int, str], list[dict]], seed: int, path: Path
) -> None:
    """Every iteration's path over the track (paper Figs. 5-9): a row per reference line,
    a column per run of :data:`RUN_KINDS` that was driven: without the filter, with it fed
    the perceived state (chance constraints, the conformal interval, the generic model),
    and fed the true state."""
    track = Track.load(setting.track)
    kinds = [kind for kind, _, _ in RUN_KINDS if any(key[2] == kind for key in rows)]
    figure, axes = plt.subplots(len(TASKS), len(kinds), figsize=(5 * len(kinds), 4.2 * len(TASKS)))
    for i, task in enumerate(TASKS):
        for j, kind in enumerate(kinds):
            ax = axes[i, j]
            plot_track(ax, track)
            runs = rows.get((task, seed, kind), [])
            colours = plt.cm.viridis(np.linspace(0, 1, max(len(runs), 2)))
            for row, colour in zip(runs, colours, strict=False):
                style = "--" if row["iteration"] == 0 else "-"
                label = "0 (expert)" if row["iteration"] == 0 else str(row["iteration"])
                label += "" if row["completed"] else "*"
                plot_path(ax, row["trajectory"], style, color=colour, lw=1.1, label=label)
            ax.set_title(f"{task}, {RUN_LABELS[kind]}")
            ax.legend(
                fontsize=7,
                title="iteration",
                title_fontsize=7,
                ncol=6,
                loc="upper center",
                bbox_to_anchor=(0.5, 0.0),
            )
            ax.set_axis_off()
    figure.suptitle(
        f"{setting.title}, seed {seed} (*: did not complete the lap; x: outside the lane)"
    )
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
