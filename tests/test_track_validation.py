"""Bad track files give one clear error naming the problem and the line."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli
from track_shapes import paperclip

from saferace.errors import TrackError
from saferace.track import Track
from saferace.track.track_io import write_track_csv
from saferace.track.validation import LEG_GAP_M

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
    # a C: 28 of a circle's 40 points, the last 117 degrees short of the first: a chord of
    # 2 x 5 m x sin(58.5 deg) = 8.53 m, the spacing 2 x 5 m x sin(4.5 deg) = 0.78 m
    "open polyline": (
        [HEADER, *circle_rows()[:28]],
        r"line 29: the last point is 8\.53 m from the first \(line 2\), where neighbouring "
        r"points are 0\.78 m apart: the points do not close a loop",
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
        Track.load(write(tmp_path, lines), strict=True)


def test_an_open_polyline_is_refused_without_strict_too_and_a_loop_closing_in_a_step_loads(
    tmp_path: Path,
):
    lines, pattern = BAD_FILES["open polyline"]
    with pytest.raises(TrackError, match=pattern):
        Track.load(write(tmp_path, lines))
    closing = [HEADER, *circle_rows()[:39]]  # one point short: the gap is two spacings
    assert Track.load(write(tmp_path, closing, "closing.csv")).length_m > 30.0


def figure_eight(count: int = 80) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    return 8.0 * np.sin(t), 4.0 * np.sin(2.0 * t)


def test_self_intersecting_centerline_is_rejected(tmp_path: Path):
    x, y = figure_eight()
    path = tmp_path / "eight.csv"
    write_track_csv(path, x, y, 0.4, 0.4)
    with pytest.raises(
        TrackError, match=r"the center line crosses itself between line \d+ and line \d+"
    ) as raised:
        Track.load(path)
    assert str(raised.value).count(str(path)) == 1  # the file is named once
    assert str(raised.value).startswith(f"{path}: ")


@pytest.mark.parametrize("strict", [False, True])
def test_a_figure_eight_sampled_right_at_its_crossing_is_named_as_crossing(
    tmp_path: Path, strict: bool
):
    """366 m long, so the check's samples are 1/2000 of the lap apart and land exactly on
    the crossing at its first data point (s = 0) and again at half the lap: the two passes
    only touch there, and the lane was narrowed to nothing before."""
    t = np.linspace(0.0, 2.0 * np.pi, 200, endpoint=False)
    x, y = 60.0 * np.sin(t), 30.0 * np.sin(2.0 * t)
    x[100] = y[100] = 0.0
    path = tmp_path / "big_eight.csv"
    write_track_csv(path, x, y, 1.0, 1.0)
    with pytest.raises(TrackError, match="the center line crosses itself between line 2 and"):
        Track.load(path, strict=strict)


def test_overlapping_boundaries_are_rejected_when_strict():
    """A hairpin whose two legs are closer than the lane width: boundaries cross."""
    t = np.linspace(0.0, 2.0 * np.pi, 200, endpoint=False)
    x, y = 10.0 * np.cos(t), 0.4 * np.sin(t)
    with pytest.raises(TrackError, match=r"(boundary crosses itself|turn radius)"):
        Track.from_arrays(x, y, 0.5, 0.5, strict=True)


def test_legs_closer_than_the_lane_are_clipped_to_either_side_of_the_line_between(caplog):
    """Straights 2 m apart with 1.2 m half widths (Montreal's hairpin: 1.9 m and 1.1 m)."""
    x, y = paperclip(legs_apart_m=2.0)
    with pytest.raises(TrackError):
        Track.from_arrays(x, y, 1.2, 1.2, strict=True)
    with caplog.at_level(logging.WARNING, logger="saferace.track.track"):
        track = Track.from_arrays(x, y, 1.2, 1.2, name="paperclip")
    assert "two legs of the track come closer than the lane" in caplog.records[0].message
    s = track.centerline.sample(0.05)
    center = track.centerline.position(s)
    w_right, w_left = track.widths(s)
    left, _ = track.boundaries_at(s)
    middle = np.abs(center[:, 0]) < 2.0  # 2 m and more from either turn
    bottom, top = left[middle & (center[:, 1] < 0.0)], left[middle & (center[:, 1] > 0.0)]
    apart = np.hypot(*(bottom[:, None, :] - top[None, :, :]).transpose(2, 0, 1)).min()
    assert LEG_GAP_M - 0.002 < apart < LEG_GAP_M + 0.01  # clipped to the gap, no further
    assert np.all(w_right[middle] == 1.2)  # the outer boundaries keep their width
    assert np.allclose(w_left[middle], (2.0 - LEG_GAP_M) / 2.0, atol=0.002)
    assert track.narrowing.points == track.point_count


def hairpin(radius_m: float, count: int = 240) -> tuple[np.ndarray, np.ndarray]:
    """A 30 m stadium whose right-hand end is a semicircle of ``radius_m``, the left one 4 m."""
    s = np.linspace(0.0, 1.0, count, endpoint=False)
    theta = 2.0 * np.pi * s
    x = np.where(np.cos(theta) > 0.0, 12.0 + radius_m * np.cos(theta), -12.0 + 4.0 * np.cos(theta))
    y = np.where(np.cos(theta) > 0.0, radius_m * np.sin(theta), 4.0 * np.sin(theta))
    points = np.column_stack([x, y])
    step = np.hypot(*np.diff(np.vstack([points, points[:1]]), axis=0).T)
    arc = np.concatenate([[0.0], np.cumsum(step)])  # resample evenly along the outline
    even = np.linspace(0.0, arc[-1], count, endpoint=False)
    return np.interp(even, arc, np.append(x, x[0])), np.interp(even, arc, np.append(y, y[0]))


def test_a_hairpin_tighter_than_the_half_width_is_narrowed_with_one_warning(caplog):
    x, y = hairpin(radius_m=0.8)
    with pytest.raises(TrackError, match="the left boundary folds over itself"):
        Track.from_arrays(x, y, 1.0, 1.0, strict=True)
    with caplog.at_level(logging.WARNING, logger="saferace.track.track"):
        track = Track.from_arrays(x, y, 1.0, 1.0, name="hairpin warned once")
        again = Track.from_arrays(x, y, 1.0, 1.0, name="hairpin warned once")  # no repeat
    (warning,) = caplog.records
    assert f"narrowed the lane at {track.narrowing.points} of 240 points" in warning.message
    assert again.narrowing == track.narrowing
    assert 0.0 < track.narrowing.max_m < 1.0
    s = track.centerline.knot_s_m[:-1]
    kappa = track.centerline.curvature(s)
    w_right, w_left = track.widths(s)
    assert np.all(w_left * np.maximum(kappa, 0.0) < 1.0)  # the inner boundary no longer folds
    assert np.max(w_left * kappa) > 0.9  # and is not narrowed much further than that
    assert np.all(w_right == 1.0)  # the outer boundary is left alone
    far = np.abs(track.centerline.position(s)[:, 0]) < 5.0  # the straights keep their width
    assert np.all(w_left[far] == 1.0)
    assert track.narrowing.points < 60


def test_a_track_that_does_not_fold_is_not_narrowed(caplog):
    with caplog.at_level(logging.WARNING, logger="saferace.track.track"):
        track = Track.from_arrays(*hairpin(radius_m=1.5), 1.0, 1.0)
    assert track.narrowing.points == 0 and not caplog.records


def test_track_info_reports_the_narrowing_and_the_racing_lines_gain(tmp_path: Path):
    path, plot = tmp_path / "hairpin.csv", tmp_path / "hairpin.png"
    write_track_csv(path, *hairpin(radius_m=0.8), 1.0, 1.0)
    result = run_cli("track-info", str(path), "--plot", str(plot))
    assert result.returncode == 0, result.stderr
    values = {
        cells[1].strip(): cells[2].strip()
        for line in result.stdout.splitlines()
        if len(cells := line.split("|")) == 4
    }
    track = Track.load(path)
    assert int(values["points narrowed (turns tighter than the half width)"]) == (
        track.narrowing.points
    )
    assert float(values["most narrowed [m]"]) == pytest.approx(track.narrowing.max_m, abs=1e-3)
    radius = float(values["tightest centre-line radius [m]"])
    assert radius == pytest.approx(track.min_turn_radius_m(), abs=1e-3) and radius < 1.0
    assert float(values["racing line: faster by [%]"]) > 0.0
    assert plot.stat().st_size > 10_000
    refused = run_cli("track-info", str(path), "--strict")
    assert refused.returncode != 0 and "folds over itself" in refused.stderr


def test_missing_file_and_unknown_name():
    with pytest.raises(TrackError, match="cannot read track file"):
        Track.load("does/not/exist.csv")
    with pytest.raises(TrackError, match=r"unknown track 'monza'.*oval"):
        Track.load("monza")


@pytest.mark.parametrize("case", ["not a number", "tight turn", "wrong column", "open polyline"])
def test_cli_reports_one_line_without_traceback(tmp_path: Path, case: str):
    lines, _ = BAD_FILES[case]
    path = write(tmp_path, lines)
    result = subprocess.run(
        [sys.executable, "-m", "saferace", "raceline", str(path), "--strict"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    error_lines = result.stderr.strip().splitlines()
    assert len(error_lines) == 1
    assert error_lines[0].startswith("saferace raceline: error: ")
    assert str(path) in error_lines[0]


def test_segments_that_touch_cross_and_segments_on_one_line_apart_do_not():
    from saferace.track.validation import _segments_cross

    p1, p2 = np.array([0.0, 0.0]), np.array([2.0, 0.0])
    others = np.array([[[1.0, 0.0], [1.0, 1.0]],  # an end on p1-p2: a T
                       [[1.0, -1.0], [1.0, 1.0]],  # a proper crossing
                       [[3.0, 0.0], [4.0, 0.0]],  # on the same line, apart
                       [[1.0, 0.5], [1.0, 1.0]]])  # fmt: skip
    assert _segments_cross(p1, p2, others[:, 0], others[:, 1]).tolist() == [
        True, True, False, False
    ]  # fmt: skip
