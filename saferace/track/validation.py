"""Checks that a centerline with widths describes a drivable closed lane.

Each check raises :class:`TrackError` naming the problem and the row where it is,
so that a researcher can fix a track file without reading our code.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from saferace.errors import TrackError

MIN_POINTS = 10

#: Describes row ``i`` in an error message, e.g. "line 12" for a file.
RowName = Callable[[int], str]


def default_row_name(index: int) -> str:
    """Row names for tracks given as arrays: zero-based point indices."""
    return f"point {index}"


def check_points(
    x_m: np.ndarray, y_m: np.ndarray, w_right_m: np.ndarray, w_left_m: np.ndarray, row: RowName
) -> None:
    """Checks on the raw rows: count, finiteness, positive widths, distinct points."""
    arrays = {"x_m": x_m, "y_m": y_m, "w_tr_right_m": w_right_m, "w_tr_left_m": w_left_m}
    lengths = {len(a) for a in arrays.values()}
    if len(lengths) != 1:
        raise TrackError(f"x, y and width arrays differ in length: {sorted(lengths)}")
    if len(x_m) < MIN_POINTS:
        raise TrackError(f"a track needs at least {MIN_POINTS} points, got {len(x_m)}")
    for name, values in arrays.items():
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise TrackError(f"{row(int(bad[0]))}: {name} is {values[bad[0]]}, not a finite number")
    for name in ("w_tr_right_m", "w_tr_left_m"):
        bad = np.flatnonzero(arrays[name] <= 0.0)
        if bad.size:
            raise TrackError(
                f"{row(int(bad[0]))}: {name} = {arrays[name][bad[0]]:g} m; widths must be positive"
            )
    step = np.hypot(np.diff(x_m), np.diff(y_m))
    repeated = np.flatnonzero(step < 1e-6)
    if repeated.size:
        raise TrackError(
            f"{row(int(repeated[0]) + 1)}: repeats the previous point; remove duplicate points"
        )


def check_lane_width(
    w_right_m: np.ndarray, w_left_m: np.ndarray, car_width_m: float, row: RowName
) -> None:
    """The lane must be wider than the car everywhere."""
    width = w_right_m + w_left_m
    narrow = np.flatnonzero(width <= car_width_m)
    if narrow.size:
        i = int(narrow[0])
        raise TrackError(
            f"{row(i)}: lane is {width[i]:.3f} m wide, narrower than the car ({car_width_m:.3f} m)"
        )


def check_turn_radius(
    curvature_radpm: np.ndarray, w_right_m: np.ndarray, w_left_m: np.ndarray, row: RowName
) -> None:
    """The inner boundary of a turn must not fold over: radius > inner half width."""
    inner = np.where(curvature_radpm > 0.0, w_left_m, w_right_m)
    folded = np.flatnonzero(np.abs(curvature_radpm) * inner >= 1.0)
    if folded.size:
        i = int(folded[0])
        side = "left" if curvature_radpm[i] > 0 else "right"
        raise TrackError(
            f"{row(i)}: turn radius {1.0 / abs(curvature_radpm[i]):.3f} m is smaller than the "
            f"{side} half width {inner[i]:.3f} m, so the {side} boundary folds over itself"
        )


#: How much tighter than the turn radius a narrowed inner half width is (m): the inner
#: boundary then still turns on a radius of at least this much.
FOLD_MARGIN_M = 0.05
#: How fast a narrowed lane returns to its width along the centerline (m per m). A dent in
#: the boundary much steeper makes it cross itself beside the turn; at 0.2 a car riding the
#: inner edge into a narrowed turn met the boundary at about 45 degrees (the inner edge is
#: short, ``ds_edge = (1 - kappa w) ds``) and no filter could turn it away in time
#: (Silverstone); 0.1 gives the same racing lines on the F1TENTH circuits.
NARROWING_SLOPE = 0.1


@dataclass(frozen=True)
class Narrowing:
    """Where :func:`narrow_folding_widths` narrowed the lane: how many points (``indices``
    into the track's points), by how much at most."""

    points: int = 0
    max_m: float = 0.0
    indices: tuple[int, ...] = ()


#: Nothing narrowed.
NOT_NARROWED = Narrowing()


def narrow_folding_widths(
    curvature_radpm: np.ndarray,
    segment: np.ndarray,
    point_s_m: np.ndarray,
    length_m: float,
    w_right_m: np.ndarray,
    w_left_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, Narrowing]:
    """Narrow each turn's inner half width to ``radius - FOLD_MARGIN_M`` where it is wider.

    Real circuits given with one fixed lane width (the F1TENTH collection's 2.2 m) have a
    few turns tighter than the half width: there the inner boundary would fold over itself.
    ``curvature_radpm`` is sampled densely along the centerline, ``segment`` says between
    which two input points each sample lies (``i``: points ``i`` and ``i + 1``, wrapping).
    Widths are linear between points, so each point's width is capped by the tightest turn
    of the two segments it bounds, and the cap widens again at ``NARROWING_SLOPE`` on either
    side: the smallest change that keeps the boundaries from folding or crossing, with a
    margin. Outer boundaries and points away from a too-tight turn keep their widths.
    """
    count = len(w_right_m)
    tightest_left, tightest_right = np.zeros(count), np.zeros(count)
    np.maximum.at(tightest_left, segment, np.maximum(curvature_radpm, 0.0))
    np.maximum.at(tightest_right, segment, np.maximum(-curvature_radpm, 0.0))

    gap = np.abs(point_s_m[:, None] - point_s_m[None, :])
    distance = np.minimum(gap, length_m - gap)  # along the closed centerline

    def capped(width: np.ndarray, tightest_on_segment: np.ndarray) -> np.ndarray:
        tightest = np.maximum(tightest_on_segment, np.roll(tightest_on_segment, 1))
        radius = 1.0 / np.maximum(tightest, 1e-12)
        folds = np.flatnonzero(width > radius)
        if not folds.size:
            return width
        limit = np.maximum(radius[folds] - FOLD_MARGIN_M, 0.0)
        cap = np.min(limit[None, :] + NARROWING_SLOPE * distance[:, folds], axis=1)
        return np.minimum(width, cap)

    new_right, new_left = capped(w_right_m, tightest_right), capped(w_left_m, tightest_left)
    cut = (w_left_m - new_left) + (w_right_m - new_right)
    narrowed = np.flatnonzero(cut > 0.0)
    narrowing = Narrowing(len(narrowed), float(cut.max(initial=0.0)), tuple(narrowed.tolist()))
    return new_right, new_left, narrowing


def check_no_self_intersection(name: str, polyline: np.ndarray, row_of_segment: RowName) -> None:
    """A closed polyline must not cross itself (adjacent segments may touch)."""
    crossing = first_self_intersection(polyline)
    if crossing is not None:
        i, j = crossing
        raise TrackError(
            f"the {name} crosses itself between {row_of_segment(i)} and {row_of_segment(j)}"
        )


def first_self_intersection(polyline: np.ndarray) -> tuple[int, int] | None:
    """Indices ``(i, j)`` of the first pair of crossing segments of a closed polyline, or None.

    Segment ``i`` joins point ``i`` to point ``i + 1`` (wrapping). Vectorised over one
    segment against all others: O(n^2) work, O(n) memory.
    """
    a = polyline
    b = np.roll(polyline, -1, axis=0)
    n = len(a)
    for i in range(n - 2):
        others = np.arange(i + 2, n if i > 0 else n - 1)
        if others.size == 0:
            continue
        if _segments_cross(a[i], b[i], a[others], b[others]).any():
            j = int(others[np.argmax(_segments_cross(a[i], b[i], a[others], b[others]))])
            return i, j
    return None


def _segments_cross(p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Whether segment p1-p2 properly crosses each segment q1-q2."""

    def orient(a, b, c):
        return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (
            c[..., 0] - a[..., 0]
        )

    d1 = orient(q1, q2, p1)
    d2 = orient(q1, q2, p2)
    d3 = orient(p1, p2, q1)
    d4 = orient(p1, p2, q2)
    return (d1 * d2 < 0.0) & (d3 * d4 < 0.0)
