"""Bad track files give one clear error naming the problem and the line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from saferace.errors import TrackError
from saferace.track import Track
from saferace.track.track_io import write_track_csv

HEADER = "# x_m,y_m,w_tr_right_m,w_tr_left_m"


def circle_rows(count: int = 40, radius: float = 5.0, width: float = 0.5) -> list[str]:
    theta = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    return [f"{radius * np.cos(t):.6f},{radius * np.sin(t):.6f},{width},{width}" for t in theta]


def write(tmp_path: Path, lines: list[str], name: str = "bad.csv") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_good_file_loads_with_either_separator_and_without_hash(tmp_path: Path):
    comma = Track.load(write(tmp_path, [HEADER, *circle_rows()], "comma.csv"))
    semicolon_rows = [row.replace(",", ";") for row in circle_rows()]
    semicolon = Track.load(
        write(tmp_path, ["x_m;y_m;w_tr_right_m;w_tr_left_m", *semicolon_rows], "semi.csv")
    )
    assert comma.length_m == pytest.approx(semicolon.length_m)
    assert comma.name == "comma"


def test_columns_may_come_in_any_order(tmp_path: Path):
    rows = [",".join(reversed(row.split(","))) for row in circle_rows()]
    track = Track.load(write(tmp_path, ["w_tr_left_m,w_tr_right_m,y_m,x_m", *rows]))
    assert track.length_m == pytest.approx(2 * np.pi * 5.0, rel=1e-4)


def corrupt(rows: list[str], index: int, column: int, value: str) -> list[str]:
    fields = rows[index].split(",")
    fields[column] = value
    return [*rows[:index], ",".join(fields), *rows[index + 1 :]]


BAD_FILES = {
    "missing column": (
        ["# x_m,y_m,w_tr_right_m", *[r.rsplit(",", 1)[0] for r in circle_rows()]],
        r"line 1: missing column\(s\) w_tr_left_m",
    ),
    "wrong column": (
        ["# x,y_m,w_tr_right_m,w_tr_left_m", *circle_rows()],
        r"line 1: missing column\(s\) x_m; unknown column\(s\) 'x'",
    ),
    "empty": ([], "empty"),
    "too few points": ([HEADER, *circle_rows(count=8)], "at least 10 points, got 8"),
    "not a number": (
        [HEADER, *corrupt(circle_rows(), 4, 1, "abc")],
        r"line 6: y_m = 'abc' is not a number",
    ),
    "nan": ([HEADER, *corrupt(circle_rows(), 6, 0, "nan")], "line 8: x_m = nan is not finite"),
    "inf": (
        [HEADER, *corrupt(circle_rows(), 2, 2, "inf")],
        "line 4: w_tr_right_m = inf is not finite",
    ),
    "zero width": (
        [HEADER, *corrupt(circle_rows(), 9, 3, "0")],
        "line 11: w_tr_left_m = 0 m; widths must be positive",
    ),
    "negative width": (
        [HEADER, *corrupt(circle_rows(), 3, 2, "-0.2")],
        "line 5: w_tr_right_m = -0.2 m",
    ),
    "short row": (
        [HEADER, *circle_rows()[:5], "1.0,2.0,0.5", *circle_rows()[5:]],
        "line 7: expected 4 values",
    ),
    "narrow lane": (
        [HEADER, *corrupt(corrupt(circle_rows(), 12, 2, "0.1"), 12, 3, "0.1")],
        r"line 14: lane is 0.200 m wide, narrower than the car \(0.300 m\)",
    ),
    "tight turn": (
        [HEADER, *circle_rows(radius=0.9, width=1.0)],
        r"line \d+: turn radius 0\.8\d+ m is smaller than the left half width 1.000 m",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_file_is_rejected_with_a_specific_message(tmp_path: Path, case: str):
    lines, pattern = BAD_FILES[case]
    with pytest.raises(TrackError, match=pattern):
        Track.load(write(tmp_path, lines))


def figure_eight(count: int = 80) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    return 8.0 * np.sin(t), 4.0 * np.sin(2.0 * t)


def test_self_intersecting_centerline_is_rejected(tmp_path: Path):
    x, y = figure_eight()
    path = tmp_path / "eight.csv"
    write_track_csv(path, x, y, 0.4, 0.4)
    with pytest.raises(
        TrackError, match=r"the center line crosses itself between .*line \d+ and .*line \d+"
    ):
        Track.load(path)


def test_overlapping_boundaries_are_rejected():
    """A hairpin whose two legs are closer than the lane width: boundaries cross."""
    t = np.linspace(0.0, 2.0 * np.pi, 200, endpoint=False)
    x, y = 10.0 * np.cos(t), 0.6 * np.sin(t) + 0.0 * t
    with pytest.raises(TrackError, match=r"(boundary crosses itself|turn radius)"):
        Track.from_arrays(x, y, 0.5, 0.5)


def test_missing_file_and_unknown_name():
    with pytest.raises(TrackError, match="cannot read track file"):
        Track.load("does/not/exist.csv")
    with pytest.raises(TrackError, match=r"unknown track 'monza'.*oval"):
        Track.load("monza")


@pytest.mark.parametrize("case", ["not a number", "tight turn", "wrong column"])
def test_cli_reports_one_line_without_traceback(tmp_path: Path, case: str):
    lines, _ = BAD_FILES[case]
    path = write(tmp_path, lines)
    result = subprocess.run(
        [sys.executable, "-m", "saferace", "raceline", str(path)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    error_lines = result.stderr.strip().splitlines()
    assert len(error_lines) == 1
    assert error_lines[0].startswith("saferace: error: ")
    assert str(path) in error_lines[0]
