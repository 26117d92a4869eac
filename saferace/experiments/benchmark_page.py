"""The benchmark's leaderboard: a table of submissions (markdown, CSV) and one HTML page.

The page is self-contained (a group can publish the file alone): the table sorts by any
column with a click (a few lines of inline JavaScript), and each track's driven paths of
every agent (unfiltered, first seed, every task and set of opponents) are embedded as PNG
images. Submissions of an older suite version keep their own scores and
rank among their own version, below the newer; submissions driven under sensor faults rank
among those of the same faults.
"""

from __future__ import annotations

import base64
import html
import io

import numpy as np

from saferace.eval.metrics import longest_standstill
from saferace.experiments.benchmark import Suite
from saferace.experiments.replay_record import replay_faults

COLUMNS = (
    "rank",
    "agent",
    "suite",
    "agent hash",
    "verified runs",
    "score",
    "score with filter",
    "traffic score",
    "at-fault collisions",
    "at-fault collisions with filter",
    "overtakes",
    "interventions [%]",
    "completion [%]",
    "lap time / expert",
    "outside lane [s]",
    "longest standstill [s]",
    "longest standstill with filter [s]",
    "runs",
)


def leaderboard_rows(submissions: list[dict]) -> list[list]:
    """One row per checked submission (see :mod:`~saferace.experiments.submission_checks`),
    the newest suite version first and, within a version, the best score first (its
    unfiltered score; see the protocol): ranks count within a version, whose scores alone
    compare. A submission's ``"verification"``, when :mod:`~saferace.experiments.verify`
    left a record for it, says how many of its runs were replayed; the traffic columns are
    empty for a suite without traffic runs. Beside completion and the time outside the
    lane, the longest any run stood still while the driver asked to move, without and with
    the filter: read from the rows, scoring nothing, and empty (``-``) for a submission
    whose rows predate it. A submission driven under faults ranks among those of the same
    faults and version alone."""
    ordered = sorted(
        submissions,
        key=lambda s: (
            -s["suite_version"],
            replay_faults(s["replay"]),
            -(s["score"] if s["score"] is not None else -1),
        ),
    )
    rows = []
    rank, board = 0, None
    for entry in ordered:
        faults = replay_faults(entry["replay"])
        rank = 1 if (entry["suite_version"], faults) != board else rank + 1
        board = (entry["suite_version"], faults)
        plain = [row for row in entry["rows"] if row["filter"] == "none"]
        filtered = [row for row in entry["rows"] if row["filter"] != "none"]
        ratios = [row["lap_time_ratio"] for row in plain if row.get("lap_time_ratio") is not None]
        rate = entry["intervention_rate"]
        record = entry.get("verification")
        rows.append(
            [
                rank,
                entry["agent"],
                suite_words(entry["suite_version"], faults),
                entry["replay"]["agent_sha256"][:12],
                f"{len(record['replayed'])} of {record['total_runs']}" if record else "no",
                entry["score"],
                entry["score_with_filter"],
                entry.get("traffic_score"),
                entry.get("at_fault_collisions"),
                entry.get("at_fault_collisions_with_filter"),
                entry.get("overtakes"),
                None if rate is None else 100.0 * rate,
                None if entry["completion"] is None else 100.0 * entry["completion"],
                float(np.mean(ratios)) if ratios else None,
                entry["time_outside_lane_s"],
                longest_standstill(plain),
                longest_standstill(filtered),
                len(entry["rows"]),
            ]
        )
    return rows


def suite_words(version: int, faults: tuple[str, ...]) -> str:
    """The board a submission ranks on: its suite version, and the faults it drove under."""
    return f"v{version}" + (f" under {' '.join(faults)}" if faults else "")


def trajectory_images(submissions: list[dict], suite: Suite) -> dict[str, str]:
    """Per track, a base64 PNG of every agent's unfiltered paths (first seed) over it: one
    panel alone on the track and, where the suite has traffic runs, one among opponents;
    a colour per agent, a line style per task or opponent, the legend below."""
    from saferace.eval.track_plots import legend_outside, plot_path, plot_track, plt
    from saferace.track import Track

    traffic = suite.traffic
    panels = [("alone", tuple(suite.tasks))]
    if traffic is not None:
        panels.append((f"{traffic.task} among opponents", tuple(traffic.opponents)))
    styles = ("-", "--", ":", "-.")
    images = {}
    for track_name in suite.tracks:
        figure = plt.figure(figsize=(5.5 * len(panels), 5.5), layout="constrained")
        axes = figure.subplots(1, len(panels), squeeze=False)[0]
        track = Track.load(suite.track_argument(track_name))
        for axis, (title, _) in zip(axes, panels, strict=True):
            plot_track(axis, track)
            axis.set_title(f"{track_name}, {title}: no filter (x: outside the lane)", fontsize=9)
        drawn = False
        for number, entry in enumerate(submissions):
            for row in entry["rows"]:
                first_plain = row["filter"] == "none" and row["seed"] == suite.seeds[0]
                if row["track"] != track_name or not first_plain or "trajectory" not in row:
                    continue
                in_traffic = row.get("opponents") is not None
                kind = row["opponents"] if in_traffic else row["task"]
                kinds = panels[int(in_traffic)][1]
                plot_path(
                    axes[int(in_traffic)],
                    row["trajectory"],
                    styles[kinds.index(kind) % len(styles)],
                    lw=1.2,
                    color=f"C{number % 10}",
                    label=f"{entry['agent']} ({'vs ' if in_traffic else ''}{kind})",
                )
                drawn = True
        if not drawn:
            plt.close(figure)
            continue
        legend_outside(figure, list(axes), ncol=4, fontsize=7)
        buffer = io.BytesIO()
        figure.savefig(buffer, format="png", dpi=90)
        plt.close(figure)
        images[track_name] = base64.b64encode(buffer.getvalue()).decode("ascii")
    return images


SORT_SCRIPT = """
document.querySelectorAll("th").forEach((header, column) => {
  header.addEventListener("click", () => {
    const body = header.closest("table").tBodies[0];
    const ascending = header.dataset.order !== "asc";
    header.dataset.order = ascending ? "asc" : "desc";
    const value = (row) => {
      const text = row.cells[column].textContent.trim();
      const number = parseFloat(text);
      return isNaN(number) ? text : number;
    };
    const rows = Array.from(body.rows).sort((a, b) => {
      const x = value(a), y = value(b);
      const numbers = typeof x === "number" && typeof y === "number";
      const order = numbers ? x - y : String(x).localeCompare(String(y));
      return ascending ? order : -order;
    });
    rows.forEach((row) => body.appendChild(row));
  });
});
"""


def leaderboard_html(submissions: list[dict], suite: Suite) -> str:
    """The self-contained leaderboard page."""
    figures = "".join(
        f'<figure><img alt="{html.escape(track)}" src="data:image/png;base64,{data}">'
        f"<figcaption>{html.escape(track)}</figcaption></figure>"
        for track, data in trajectory_images(submissions, suite).items()
    )
    return html_page(
        f"SafeRace leaderboard, suite v{suite.version}",
        f"""<h1>SafeRace leaderboard</h1>
<p>Suite v{suite.version}: {len(suite.tracks)} tracks, {len(suite.tasks)} tasks,
{len(suite.seeds)} starts{_traffic_words(suite)}, without and with the shared safety
filter. Score: 100 times the mean over the unfiltered runs of completion x speed against
the expert x exp(-seconds outside the lane){_penalty_words(suite)}, recomputed from every
run's measurements. Longest standstill: the longest any run stood still while its driver
asked to move (not scored; it shows a car kept in its lane by being held still), without
and with the filter. Overtakes: opponents an agent passed and stayed ahead of. Submissions
of an older suite rank among their own version only. Verified runs: how many of an entry's
runs <code>saferace verify</code> drove again and found as submitted. Click a column to
sort.</p>
{sortable_table("leaderboard", COLUMNS, leaderboard_rows(submissions))}
<h2>Driven paths</h2>
{figures}""",
    )


def html_page(title: str, body: str) -> str:
    """A self-contained page of ``body`` (HTML), its tables sortable by a click."""
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>{html.escape(title)}</title>
<style>
body {{ font-family: sans-serif; margin: 2em; }}
.scroll {{ overflow-x: auto; }}
table {{ border-collapse: collapse; font-size: 0.9em; }}
th, td {{ border: 1px solid #999; padding: 4px; text-align: right; }}
th {{ cursor: pointer; background: #eee; max-width: 7em; vertical-align: bottom; }}
figure {{ display: inline-block; margin: 0.5em; }}
</style></head><body>
{body}
<script>{SORT_SCRIPT}</script>
</body></html>
"""


def sortable_table(table_id: str, columns: tuple[str, ...], rows: list[list]) -> str:
    """A table of ``rows`` under ``columns``, every cell escaped."""
    header = "".join(f"<th>{html.escape(name)}</th>" for name in columns)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(cell(value))}</td>" for value in row) + "</tr>"
        for row in rows
    )
    return (
        f'<div class="scroll"><table id="{table_id}"><thead><tr>{header}</tr></thead>'
        f"<tbody>{body}</tbody></table></div>"
    )


def _traffic_words(suite: Suite) -> str:
    traffic = suite.traffic
    if traffic is None:
        return ""
    return (
        f"; in traffic, {traffic.task} behind each of {len(traffic.opponents)} opponents "
        f"({', '.join(traffic.opponents)}), {traffic.laps} laps"
    )


def _penalty_words(suite: Suite) -> str:
    traffic = suite.traffic
    if traffic is None:
        return ""
    return f" x {traffic.collision_factor:g} per collision the agent caused"


def cell(value: object) -> str:
    if value is None:
        return "-"
    return f"{value:.3f}" if isinstance(value, float) else str(value)
