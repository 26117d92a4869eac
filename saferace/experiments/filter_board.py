"""The safety filters' board: checked filter submissions ranked (markdown, CSV, one HTML
page) and a picture of each entry's score and time outside per condition.

Entries rank by their score within their protocol version (newest first); beside it the
score under the true state, the noisy state and the perception, how many runs left the
lane and for how long (under the true state apart: no filter should leave there), the
at-fault collisions, the longest standstill, the interventions, the answers clipped to the
car's limits and the runs whose filter raised.
"""

from __future__ import annotations

import base64
import io
import math
from pathlib import Path

from saferace.experiments.benchmark_page import html_page, sortable_table
from saferace.experiments.filter_suite import FilterSuite

COLUMNS = (
    "rank",
    "entry",
    "protocol",
    "entry hash",
    "verified runs",
    "score",
    "score, true state",
    "score, noisy state",
    "score, perceived",
    "runs outside",
    "outside, true state [s]",
    "outside [s]",
    "at-fault collisions",
    "longest standstill [s]",
    "interventions [%]",
    "clipped steps",
    "filter errors",
    "runs",
)


def filter_board_rows(submissions: list[dict]) -> list[list]:
    """One row per checked filter submission (see
    :mod:`~saferace.experiments.filter_submission_checks`), the newest protocol first and,
    within it those with the circuits' runs first, then the best score first; ranks count
    within a version, with or without the circuits. A submission's
    ``"verification"`` (a :mod:`~saferace.experiments.verify` record) says how many of its
    runs were replayed."""
    ordered = sorted(submissions, key=lambda s: (*_board(s), -s["score"]))
    rows, rank, board = [], 0, None
    for entry in ordered:
        rank = 1 if _board(entry) != board else rank + 1
        board = _board(entry)
        version = entry["filter_suite_version"]
        record = entry.get("verification")
        rate = entry["intervention_rate"]
        rows.append(
            [
                rank,
                entry["entry"],
                f"filters v{version}" + (" + circuits" if entry.get("circuits") else ""),
                entry["replay"]["entry_sha256"][:12],
                f"{len(record['replayed'])} of {record['total_runs']}" if record else "no",
                entry["score"],
                entry["score_true"],
                entry["score_noisy"],
                entry["score_perceived"],
                entry["runs_outside"],
                entry["time_outside_true_state_s"],
                entry["time_outside_lane_s"],
                entry["at_fault_collisions"],
                entry["longest_standstill_s"],
                None if rate is None else 100.0 * rate,
                entry["clipped_steps"],
                entry["filter_errors"],
                len(entry["rows"]),
            ]
        )
    return rows


def _mean_score(rows: list[dict]) -> float:
    """100 times the rows' mean score (NaN for none: an entry without the circuits)."""
    return 100 * sum(row["score"] for row in rows) / len(rows) if rows else math.nan


def _board(submission: dict) -> tuple[int, bool]:
    """What a submission ranks among: its protocol version (newest first), then whether it
    drove the circuits too."""
    return -submission["filter_suite_version"], submission.get("circuits") is None


def plot_conditions(submissions: list[dict], suite: FilterSuite, path: Path | None = None) -> bytes:
    """Per entry (a row) and condition (a column; among opponents and on the circuits
    apart): the mean score of its runs (colour) and their time outside (written where
    any); the PNG's bytes, written to ``path`` too."""
    from saferace.eval.track_plots import plt

    columns = [(name, "") for name in suite.conditions] + [
        (name, f"{opponents} car")
        for opponents in suite.opponents
        for name in suite.traffic_conditions
    ]
    if any(entry.get("circuits") for entry in submissions):
        columns += [(name, "circuits") for name in suite.circuit_conditions]
    ordered = sorted(submissions, key=lambda s: -s["score"])
    scores, outside = [], []
    for entry in ordered:
        runs: dict[tuple, list[dict]] = {column: [] for column in columns}
        for row in entry["rows"]:
            among = "circuits" if row["track"] in suite.circuits else ""
            among = f"{row['opponents']} car" if row["opponents"] is not None else among
            runs[(row["condition"], among)].append(row)
        scores.append([_mean_score(runs[column]) for column in columns])
        outside.append([sum(r["time_outside_lane_s"] for r in runs[c]) for c in columns])
    figure, axis = plt.subplots(figsize=(1.2 * len(columns) + 4, 0.5 * len(ordered) + 2.0))
    image = axis.imshow(scores, cmap="RdYlGn", vmin=0, vmax=100, aspect="auto")
    for i, row in enumerate(outside):
        for j, seconds in enumerate(row):
            if math.isnan(scores[i][j]):
                axis.text(j, i, "not driven", ha="center", va="center", fontsize=7)
                continue
            words = f"{scores[i][j]:.0f}" + (f"\n{seconds:.1f} s out" if seconds else "")
            axis.text(j, i, words, ha="center", va="center", fontsize=7)
    names = [f"{name}, {among}" if among else name for name, among in columns]
    axis.set_xticks(range(len(columns)), names, rotation=30, ha="right", fontsize=8)
    axis.set_yticks(range(len(ordered)), [entry["entry"] for entry in ordered], fontsize=8)
    axis.set_title(
        f"Filter protocol v{suite.version}: score per condition (below 50: a run left the "
        "lane or caused a collision)\nand time outside the lane over the condition's runs",
        fontsize=9,
    )
    figure.colorbar(image, ax=axis, label="score")
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100)
    plt.close(figure)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(buffer.getvalue())
    return buffer.getvalue()


def filter_board_html(submissions: list[dict], suite: FilterSuite) -> str:
    """The self-contained page of the filters' board (the picture: the entries of
    ``suite``'s version)."""
    pictured = [entry for entry in submissions if entry["filter_suite_version"] == suite.version]
    picture = base64.b64encode(plot_conditions(pictured, suite)).decode("ascii")
    return html_page(
        f"SafeRace safety filters, protocol v{suite.version}",
        f"""<h1>SafeRace safety filters</h1>
<p>Filter protocol v{suite.version}: {", ".join(suite.drivers)} behind each filter on
{len(suite.tracks)} tracks, under {len(suite.conditions)} conditions
({", ".join(suite.conditions)}), and among opponents; {len(suite.runs())} runs (and on
{len(suite.circuits)} F1TENTH circuits for entries with them). A run scores below 50 if
the car left its lane or caused a collision, at least 50 otherwise, more for keeping the
driver's pace and changing its actions little; recomputed from every run's measurements.
Verified runs: how many of an entry's runs <code>saferace verify</code> drove again and
found as submitted. Click a column to sort.</p>
{sortable_table("filters", COLUMNS, filter_board_rows(submissions))}
<h2>Per condition</h2>
<img alt="score per condition" src="data:image/png;base64,{picture}">""",
    )
