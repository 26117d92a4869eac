"""Leaderboard tables (markdown, CSV) and trajectory plots from evaluation rows."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from saferace.eval.tables import markdown_table, write_csv

COLUMNS = (
    "agent",
    "task",
    "track",
    "seeds",
    "laps completed",
    "best lap [s]",
    "mean lap [s]",
    "mean abs dev [m]",
    "max abs dev [m]",
    "outside lane [s]",
    "steer rate RMS [rad/s]",
)


def leaderboard_rows(rows: list[dict]) -> list[list]:
    """One line per (agent, task, track), averaged over seeds, sorted by mean lap time."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for row in rows:
        groups[(row["agent"], row["task"], row["track"])].append(row["summary"])
    table = []
    for (agent, task, track), summaries in groups.items():
        best = [s["best_lap_time_s"] for s in summaries if s["best_lap_time_s"] is not None]
        worst = [
            s["max_abs_deviation_m"] for s in summaries if s["max_abs_deviation_m"] is not None
        ]
        table.append(
            [
                agent,
                task,
                track,
                len(summaries),
                sum(s["laps_completed"] for s in summaries),
                min(best) if best else None,
                _mean(summaries, "mean_lap_time_s"),
                _mean(summaries, "mean_abs_deviation_m"),
                max(worst) if worst else None,
                sum(s["time_outside_lane_s"] for s in summaries),
                _mean(summaries, "steering_rate_rms_radps"),
            ]
        )
    return sorted(table, key=lambda r: (r[2], r[1], r[6] if r[6] is not None else np.inf))


def _mean(summaries: list[dict], key: str) -> float | None:
    values = [s[key] for s in summaries if s[key] is not None]
    return float(np.mean(values)) if values else None


def leaderboard_markdown(rows: list[dict]) -> str:
    return markdown_table(
        COLUMNS, [[("-" if v is None else v) for v in r] for r in leaderboard_rows(rows)]
    )


def write_leaderboard_csv(rows: list[dict], path: str | Path) -> None:
    write_csv(path, COLUMNS, leaderboard_rows(rows))


def plot_trajectories(rows: list[dict], path: str | Path) -> None:
    """Per track: driven paths over the track (paper Fig. 4), and speed against ``s``."""
    from saferace.eval.track_plots import plot_path, plot_track, plt
    from saferace.track import Track

    by_track: dict[str, list[dict]] = defaultdict(list)
    for row in rows:
        by_track[row["config"]["track"]].append(row)
    fig, axes = plt.subplots(len(by_track), 2, figsize=(13, 5 * len(by_track)), squeeze=False)
    for (track_arg, track_rows), (ax_map, ax_speed) in zip(by_track.items(), axes, strict=True):
        track = Track.load(track_arg)
        plot_track(ax_map, track)
        for row in track_rows:
            label = f"{row['agent']} / {row['task']} / seed {row['seed']}"
            trajectory = row["trajectory"]
            plot_path(ax_map, trajectory, lw=1.2, label=label)
            ax_speed.plot(trajectory["s_m"], trajectory["v_x_mps"], ".", ms=2, label=label)
        ax_map.set_title(f"{track.name}: driven trajectories (x: outside the lane)")
        ax_map.legend(fontsize=7, loc="upper right")
        ax_speed.set_xlabel("centerline arc length s [m]")
        ax_speed.set_ylabel("speed [m/s]")
        ax_speed.set_title(f"{track.name}: speed along the track")
        ax_speed.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
