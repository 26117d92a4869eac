"""Leaderboard tables (markdown, CSV) and trajectory plots from evaluation rows.

Every table line and plot label names the safety filter and the state source it was fed,
in words (:func:`filter_words`, :func:`state_source_words`): a filtered and an unfiltered
run of the same agent are two lines, never one.
"""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import fields
from pathlib import Path

import numpy as np

from saferace.eval.filter_config import FilterConfig, users_filter, users_perception
from saferace.eval.metrics import longest_standstill
from saferace.eval.tables import markdown_table, write_csv
from saferace.names import DEFAULT_FILTER_MODELS, DEFAULT_GAINS, NOISY_SAMPLES

COLUMNS = (
    "agent",
    "task",
    "track",
    "filter",
    "state source",
    "seeds",
    "laps completed",
    "best lap [s]",
    "mean lap [s]",
    "mean abs dev [m]",
    "max abs dev [m]",
    "outside lane [s]",
    "longest standstill [s]",
    "interventions [%]",
    "steer rate RMS [rad/s]",
    "opponents",
    "at-fault collisions",
    "overtakes",
)
_MEAN_LAP = COLUMNS.index("mean lap [s]")
_FILTER_FIELDS = {field.name for field in fields(FilterConfig)}
_DEFAULT_FILTER = FilterConfig()


def row_filter(row: dict) -> FilterConfig:
    """The :class:`FilterConfig` a result row ran behind; a row without one (written before
    rows recorded it, or by ``saferace collect``) ran without a filter."""
    config = {k: v for k, v in (row.get("filter") or {}).items() if k in _FILTER_FIELDS}
    if not users_filter(str(config.get("kind", "none"))):  # ours: what older rows ran
        config.setdefault("uncertainty", "chance")
        config.setdefault("gains", DEFAULT_GAINS)
    for name in ("state_noise", "spread_scale"):
        if config.get(name) is not None:
            config[name] = tuple(config[name])
    return FilterConfig(**config)


def filter_words(config: FilterConfig) -> str:
    """The filter in words: ``none``; ``cbf`` on the true state; ``cbf, probabilistic`` or
    ``cbf, on the mean`` on uncertain state samples, ``cbf, robust over the interval`` in
    the robust mode; then any setting off its default."""
    if config.kind == "none":
        return "none"
    if users_filter(config.kind):
        noisy = "noisy state" if config.state_noise is not None else "the true state"
        return f"{config.kind} on {config.state_source or noisy}"
    parts = [config.kind]
    if config.uncertainty == "robust":
        parts.append("robust over the interval")
    elif config.uncertain_state:
        parts.append("probabilistic" if config.probabilistic else "on the mean")
        if config.probabilistic and config.eta != _DEFAULT_FILTER.eta:
            parts.append(f"eta {config.eta:g}")
    if config.gains != DEFAULT_GAINS and config.kind == "cbf":
        parts.append(f"{config.gains} gains")
    if config.model != DEFAULT_FILTER_MODELS[config.kind]:
        parts.append(f"{config.model} model")
    if config.map_curvature:
        parts.append("map curvature")
    if config.opponent_noise_m:
        parts.append(f"opponents seen with {config.opponent_noise_m:g} m noise")
    if config.slack != _DEFAULT_FILTER.slack:
        parts.append(f"{config.slack} slack")
    if config.adaptive == "oracle":
        parts.append("adaptive conformal, oracle feedback")
    elif config.adaptive is not None:
        parts.append(f"adaptive conformal, {config.adaptive} feedback")
    if config.spread_scale is not None:
        parts.append("spread x" + "/".join(f"{factor:g}" for factor in config.spread_scale))
    return ", ".join(parts)


def state_source_words(config: FilterConfig) -> str:
    """What fed the filter the lane state, in words: ``none`` (no filter), ``true state``
    (the oracle), ``noisy`` (the oracle plus noise), ``perceived`` (a state network, its
    checkpoint in brackets), ``perceived, generic`` (the generic perception model, a
    recipe other than the default in brackets) or ``perceived by MODULE:FACTORY`` (a user's
    perception method, one estimate a step); ``+ odometry`` when fused, and the samples
    when not the default (where they count)."""
    if config.kind == "none":
        return "none"
    if not config.uncertain_state:
        return "true state"
    details = []
    if config.state_source is None:
        words = "noisy"
        assert config.state_noise is not None  # neither learned nor the truth: noisy
        e_y, e_psi = config.state_noise
        details.append(f"sd {e_y:g} m, {e_psi:g} rad")
    elif users_perception(config.state_source):
        return f"perceived by {config.state_source}"
    else:
        kind, _, argument = config.state_source.partition(":")
        words = "perceived" if kind == "learned" else "perceived, generic"
        if argument:
            details.append(Path(argument).name)
    if config.samples != NOISY_SAMPLES:
        details.append(f"{config.samples} samples")
    if config.fuse_odometry:
        words += " + odometry"
    return f"{words} ({', '.join(details)})" if details else words


def filter_phrase(config: FilterConfig) -> str:
    """A legend's words for a filter setting: ``no filter``, or the filter and its state
    source (``filter: cbf, on the mean; state source: noisy (...)``)."""
    if config.kind == "none":
        return "no filter"
    return f"filter: {filter_words(config)}; state source: {state_source_words(config)}"


def row_label(row: dict) -> str:
    """A plot label that tells rows apart: agent, task, seed, filter and state source."""
    head = f"{row['agent']} / {row['task']} / seed {row.get('seed', '-')}"
    return f"{head} / {filter_phrase(row_filter(row))}"


def leaderboard_rows(rows: list[dict]) -> list[list]:
    """One line per (agent, task, track, filter, state source, opponents), averaged over
    seeds, sorted by mean lap time. The whole filter configuration keys a group: runs behind
    different filters, or among other opponents, are never merged. Beside the time outside
    the lane (summed) stand the laps completed (summed) and the longest standstill while
    the driver asked to move (the longest of the seeds'; None where a row predates it). In
    traffic, the collisions the agent caused and its overtakes are summed over the seeds."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for row in rows:
        config = row_filter(row)
        key = (
            row["agent"],
            row["task"],
            row["track"],
            json.dumps(config.as_dict()),
            " ".join(row_opponents(row)),
        )
        groups[key].append(row["summary"])
    table = []
    for (agent, task, track, config_json, opponents), summaries in groups.items():
        config = FilterConfig(**_tuples(json.loads(config_json)))
        best = [s["best_lap_time_s"] for s in summaries if s["best_lap_time_s"] is not None]
        worst = [
            s["max_abs_deviation_m"] for s in summaries if s["max_abs_deviation_m"] is not None
        ]
        rate = _mean(summaries, "intervention_rate")
        table.append(
            [
                agent,
                task,
                track,
                filter_words(config),
                state_source_words(config),
                len(summaries),
                sum(s["laps_completed"] for s in summaries),
                min(best) if best else None,
                _mean(summaries, "mean_lap_time_s"),
                _mean(summaries, "mean_abs_deviation_m"),
                max(worst) if worst else None,
                sum(s["time_outside_lane_s"] for s in summaries),
                longest_standstill(summaries),
                None if rate is None else 100.0 * rate,
                _mean(summaries, "steering_rate_rms_radps"),
                opponents or None,
                _sum(summaries, "at_fault_collisions"),
                _sum(summaries, "overtakes"),
            ]
        )
    return sorted(
        table,
        key=lambda r: (r[2], r[1], r[_MEAN_LAP] if r[_MEAN_LAP] is not None else np.inf),
    )


def _tuples(config: dict) -> dict:
    return {k: tuple(v) if isinstance(v, list) else v for k, v in config.items()}


def row_opponents(row: dict) -> list[str]:
    """The opponents a row drove among, as given (``--opponents``); ``task default`` for a
    traffic task's own, none alone on the track."""
    given = (row.get("config") or {}).get("env", {}).get("opponents")
    if given:
        return [str(spec) for spec in given]
    return ["task default"] if "at_fault_collisions" in row["summary"] else []


def _present(summaries: list[dict], key: str) -> list:
    return [s[key] for s in summaries if s.get(key) is not None]


def _sum(summaries: list[dict], key: str) -> int | None:
    values = _present(summaries, key)
    return sum(values) if values else None


def _mean(summaries: list[dict], key: str) -> float | None:
    values = _present(summaries, key)
    return float(np.mean(values)) if values else None


def leaderboard_markdown(rows: list[dict]) -> str:
    return markdown_table(
        COLUMNS, [[("-" if v is None else v) for v in r] for r in leaderboard_rows(rows)]
    )


def write_leaderboard_csv(rows: list[dict], path: str | Path) -> None:
    write_csv(path, COLUMNS, leaderboard_rows(rows))


def plot_trajectories(rows: list[dict], path: str | Path) -> None:
    """Per track: driven paths over the track (paper Fig. 4), in traffic the opponents'
    paths and the collisions too, and speed against ``s``; the legend (agent, task, seed,
    filter, state source) below the plots, off the track.

    A row finds its track wherever the plot is made (:func:`~saferace.eval.runner.row_track`).
    """
    from saferace.eval.runner import row_track, track_key
    from saferace.eval.track_plots import legend_outside, plot_path, plot_track, plt

    by_track: dict[tuple, list[tuple[int, dict]]] = defaultdict(list)
    for index, row in enumerate(rows):
        by_track[track_key(row)].append((index, row))
    height = [5.5 + 0.2 * (len(track_rows) + 1) / 2 for track_rows in by_track.values()]
    fig = plt.figure(figsize=(13, sum(height)), layout="constrained")
    panels = fig.subfigures(len(by_track), 1, height_ratios=height, squeeze=False)[:, 0]
    for track_rows, panel in zip(by_track.values(), panels, strict=True):
        ax_map, ax_speed = panel.subplots(1, 2)
        index, first = track_rows[0]
        track = row_track(first, f"row {index + 1} ({row_label(first)})")
        plot_track(ax_map, track)
        for number, group in enumerate(same_paths([row for _, row in track_rows])):
            colour, row = f"C{number % 10}", group[0]
            trajectory = row["trajectory"]
            plot_path(ax_map, trajectory, lw=1.2, color=colour, label=group_label(group))
            plot_traffic(ax_map, row.get("traffic"), colour)
            ax_speed.plot(trajectory["s_m"], trajectory["v_x_mps"], ".", ms=2, color=colour)
        ax_map.set_title(f"{track.name}: driven trajectories (x: outside the lane)")
        ax_speed.set_xlabel("centerline arc length s [m]")
        ax_speed.set_ylabel("speed [m/s]")
        ax_speed.set_title(f"{track.name}: speed along the track (colours as on the left)")
        ax_speed.grid(alpha=0.3)
        legend_outside(panel, [ax_map])
    fig.savefig(path, dpi=110)
    plt.close(fig)


def same_paths(rows: list[dict]) -> list[list[dict]]:
    """``rows`` grouped by their driven path, in order of first appearance: runs that drove
    exactly the same path (and met the same traffic) are drawn once, or the last would hide
    the others."""
    groups: dict[str, list[dict]] = {}
    for row in rows:
        path = [row["trajectory"]["x_m"], row["trajectory"]["y_m"], row.get("traffic")]
        key = json.dumps(path, default=lambda value: np.asarray(value).tolist())
        groups.setdefault(key, []).append(row)
    return list(groups.values())


def group_label(group: list[dict]) -> str:
    """The legend entry of a path that ``group``'s runs all drove."""
    labels = [row_label(row) for row in group]
    if len(labels) == 1:
        return labels[0]
    return f"{' = '.join(labels)} (the same path)"


OPPONENTS_LABEL = "opponents (dotted, in their driver's colour)"
AT_FAULT_LABEL = "collision the driver caused"
NOT_AT_FAULT_LABEL = "collision an opponent caused"


def plot_traffic(axis, traffic: dict | None, colour: str) -> None:
    """A row's opponents' paths (dotted, in ``colour``) and its collisions (stars: red where
    the row's driver caused it, orange elsewhere) on ``axis``; nothing without traffic."""
    if not traffic:
        return
    for path in traffic["opponents"]:
        axis.plot(path["x_m"], path["y_m"], ":", lw=1.0, color=colour, label=OPPONENTS_LABEL)
    for hit in traffic["collisions"]:
        axis.plot(
            hit["x_m"],
            hit["y_m"],
            "*",
            ms=12,
            mec="black",
            color="red" if hit["at_fault"] else "orange",
            zorder=5,
            label=AT_FAULT_LABEL if hit["at_fault"] else NOT_AT_FAULT_LABEL,
        )
