"""Plots of tracks and reference lines (like the paper's Fig. 2-3)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import LineCollection

from saferace.track import Track
from saferace.track.raceline import ReferenceLine


def plot_track(ax: plt.Axes, track: Track) -> None:
    """Asphalt, boundaries and start line of ``track`` on ``ax``."""
    left, right = track.boundaries()
    outline = np.vstack([left, left[:1], right[:1], right[::-1]])
    ax.fill(outline[:, 0], outline[:, 1], color="0.85", zorder=0)
    for boundary in (left, right):
        closed = np.vstack([boundary, boundary[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color="k", lw=1.0)
    start = np.vstack([left[0], right[0]])
    ax.plot(start[:, 0], start[:, 1], color="tab:red", lw=2.0, label="start/finish")
    if track.narrowing.points:
        narrowed = track.centerline.position(track.point_s_m[list(track.narrowing.indices)])
        ax.scatter(
            narrowed[:, 0], narrowed[:, 1], s=8, color="gold", edgecolors="0.35",
            linewidths=0.4, zorder=1.5,
            label=f"lane narrowed ({track.narrowing.points} points, "
            f"up to {track.narrowing.max_m:.2f} m)",
        )  # fmt: skip
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def plot_path(ax: plt.Axes, trajectory: dict, style: str = "-", **line) -> None:
    """A driven path on ``ax`` and, in its colour, a cross wherever the car was outside its
    lane (``trajectory["outside"]``, see :func:`~saferace.eval.metrics.thinned_trajectory`;
    results written before it have none), so that an exit shows on a circuit drawn small."""
    x_m, y_m = np.asarray(trajectory["x_m"]), np.asarray(trajectory["y_m"])
    (drawn,) = ax.plot(x_m, y_m, style, **line)
    outside = np.asarray(trajectory.get("outside", []), bool)
    if outside.any():
        ax.plot(x_m[outside], y_m[outside], "x", color=drawn.get_color(), ms=6, mew=1.5, zorder=4)


def legend_outside(owner, axes, ncol: int = 2, fontsize: float = 8) -> None:
    """One legend of every labelled line on ``axes`` (each label once), below the plots of
    ``owner``: a figure or subfigure made with ``layout="constrained"``, which makes room
    for it. Off the axes, the legend hides no part of a track."""
    handles, labels = [], []
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            if label not in labels:
                handles.append(handle)
                labels.append(label)
    if labels:
        owner.legend(
            handles,
            labels,
            loc="outside lower center",
            ncol=min(ncol, len(labels)),
            fontsize=fontsize,
            frameon=False,
        )


def plot_reference_lines(
    track: Track, center: ReferenceLine, racing: ReferenceLine, out_path: str | Path
) -> None:
    """Track with both lines, the racing line coloured by speed, and speed against ``s``."""
    fig, (ax_map, ax_speed) = plt.subplots(
        1, 2, figsize=(13, 6), gridspec_kw={"width_ratios": [1.4, 1.0]}, layout="constrained"
    )
    plot_track(ax_map, track)
    center_xy = center.path.position(center.s_m)
    ax_map.plot(center_xy[:, 0], center_xy[:, 1], "--", color="0.4", lw=1.0, label="center line")
    racing_xy = racing.path.position(racing.s_m)
    closed = np.vstack([racing_xy, racing_xy[:1]])
    segments = np.stack([closed[:-1], closed[1:]], axis=1)
    lines = LineCollection(list(segments), cmap="plasma", linewidths=2.5, zorder=2.5)
    lines.set_array(racing.vx_mps)
    ax_map.add_collection(lines)
    # the legend's sample of the racing line: a colour from the middle of its scale
    ax_map.plot(
        [], [], color=plt.get_cmap("plasma")(0.6), lw=2.5, label="racing line (colour: speed)"
    )
    fig.colorbar(lines, ax=ax_map, label="racing-line speed [m/s]", shrink=0.8)
    ax_map.set_title(f"{track.name}: minimum-curvature racing line")

    ax_speed.plot(
        center.center_s_m, center.center_vx_mps, "--", color="0.4", lw=1.0, label="center line"
    )
    ax_speed.plot(
        racing.center_s_m, racing.center_vx_mps, color="tab:purple", label="racing line speed"
    )
    ax_speed.set_xlabel("centerline arc length s [m]")
    ax_speed.set_ylabel("speed [m/s]")
    ax_speed.set_title(
        f"lap time: center {center.lap_time_s:.2f} s, racing {racing.lap_time_s:.2f} s"
    )
    ax_speed.grid(alpha=0.3)
    legend_outside(fig, (ax_map, ax_speed), ncol=5, fontsize=9)
    fig.savefig(out_path, dpi=120)
    plt.close(fig)
