"""Plain-text tables for the command line and for leaderboards."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A markdown table with right-aligned columns; floats are shown with 3 decimals, and a
    pipe inside a cell escaped (``max |u diff|`` would split its column)."""
    headers = [_escaped(header) for header in headers]
    cells = [[_escaped(_format(value)) for value in row] for row in rows]
    widths = [max(len(h), *(len(row[i]) for row in cells)) for i, h in enumerate(headers)]
    lines = [
        "| " + " | ".join(h.ljust(w) for h, w in zip(headers, widths, strict=True)) + " |",
        "|" + "|".join("-" * (w + 1) + ":" for w in widths) + "|",
    ]
    lines += [
        "| " + " | ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)) + " |"
        for row in cells
    ]
    return "\n".join(lines)


def or_dash(value: float | None) -> float | str:
    """A table cell: ``value``, or ``-`` where it was not measured."""
    return "-" if value is None else value


def _escaped(text: str) -> str:
    return text.replace("|", "\\|")


def _format(value: object) -> str:
    return f"{value:.3f}" if isinstance(value, float) else str(value)


def write_csv(path: str | Path, headers: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    """A CSV file of ``headers`` and ``rows``."""
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(headers)
        writer.writerows(rows)
