"""Reading and writing track centerline files.

The format is the one of the TUM racetrack-database and the F1TENTH racetracks:
a header ``x_m,y_m,w_tr_right_m,w_tr_left_m`` (optionally behind ``#``), one
row per centerline point, comma or semicolon separated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from saferace.errors import TrackError

COLUMNS = ("x_m", "y_m", "w_tr_right_m", "w_tr_left_m")


@dataclass(frozen=True)
class TrackTable:
    """Raw columns of a track file and the file line of every row (for error messages)."""

    x_m: np.ndarray
    y_m: np.ndarray
    w_right_m: np.ndarray
    w_left_m: np.ndarray
    line_numbers: np.ndarray


def read_track_csv(path: str | Path) -> TrackTable:
    """Parse a track CSV, raising :class:`TrackError` with the file and line on bad input."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise TrackError(f"{path}: cannot read track file ({exc.strerror})") from None
    lines = text.splitlines()
    header_index = next((i for i, line in enumerate(lines) if line.strip()), None)
    if header_index is None:
        raise TrackError(f"{path}: the file is empty; expected header {','.join(COLUMNS)}")
    header_line = lines[header_index].strip().lstrip("#")
    delimiter = ";" if ";" in header_line else ","
    names = [name.strip() for name in header_line.split(delimiter)]
    _check_header(path, header_index + 1, names)
    order = [names.index(column) for column in COLUMNS]

    rows: list[list[float]] = []
    line_numbers: list[int] = []
    for index in range(header_index + 1, len(lines)):
        line = lines[index].strip()
        if not line or line.startswith("#"):
            continue
        fields = [field.strip() for field in line.split(delimiter)]
        if len(fields) != len(names):
            raise TrackError(
                f"{path}: line {index + 1}: expected {len(names)} values "
                f"({delimiter.join(names)}), got {len(fields)}"
            )
        values = [_parse_number(path, index + 1, names[i], fields[i]) for i in order]
        rows.append(values)
        line_numbers.append(index + 1)
    if not rows:
        raise TrackError(f"{path}: the file has a header but no points")
    data = np.asarray(rows, dtype=float)
    return TrackTable(data[:, 0], data[:, 1], data[:, 2], data[:, 3], np.asarray(line_numbers))


def write_track_csv(
    path: str | Path,
    x_m: np.ndarray,
    y_m: np.ndarray,
    w_right_m: np.ndarray | float,
    w_left_m: np.ndarray | float,
) -> None:
    """Write a track CSV in the TUM/F1TENTH format (header behind ``#``); widths may be scalars."""
    x_m = np.asarray(x_m, dtype=float)
    widths = [np.broadcast_to(np.asarray(w, dtype=float), x_m.shape) for w in (w_right_m, w_left_m)]
    data = np.column_stack([x_m, y_m, *widths])
    np.savetxt(path, data, fmt="%.6f", delimiter=",", header=",".join(COLUMNS), comments="# ")


def _check_header(path: Path, line_number: int, names: list[str]) -> None:
    missing = [column for column in COLUMNS if column not in names]
    unknown = [name for name in names if name not in COLUMNS]
    duplicated = sorted({name for name in names if names.count(name) > 1})
    if missing or unknown or duplicated:
        problems = []
        if missing:
            problems.append(f"missing column(s) {', '.join(missing)}")
        if unknown:
            problems.append(f"unknown column(s) {', '.join(repr(n) for n in unknown)}")
        if duplicated:
            problems.append(f"repeated column(s) {', '.join(duplicated)}")
        raise TrackError(
            f"{path}: line {line_number}: {'; '.join(problems)}; "
            f"the header must be {','.join(COLUMNS)}"
        )


def _parse_number(path: Path, line_number: int, column: str, field: str) -> float:
    try:
        value = float(field)
    except ValueError:
        raise TrackError(
            f"{path}: line {line_number}: {column} = {field!r} is not a number"
        ) from None
    if not math.isfinite(value):
        raise TrackError(f"{path}: line {line_number}: {column} = {field} is not finite")
    return value
