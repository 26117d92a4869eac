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


#: How many median spacings the last point may lie from the first (see :func:`check_closed`).
MAX_CLOSING_GAP = 5.0


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
    check_closed(x_m, y_m, step, row)


def check_closed(x_m: np.ndarray, y_m: np.ndarray, step: np.ndarray, row: RowName) -> None:
    """A track is a closed loop: the last point must lie about one spacing from the first.
    A gap above :data:`MAX_CLOSING_GAP` times the median spacing, and above every other
    spacing, is an open polyline, which a straight chord would otherwise close (on the
    F1TENTH circuits and random tracks the gap is at most 1.1 spacings)."""
    gap = float(np.hypot(x_m[-1] - x_m[0], y_m[-1] - y_m[0]))
    spacing = float(np.median(step))
    if gap > MAX_CLOSING_GAP * spacing and gap > float(step.max()):
        last = len(x_m) - 1
        raise TrackError(
            f"{row(last)}: the last point is {gap:.2f} m from the first ({row(0)}), where "
            f"neighbouring points are {spacing:.2f} m apart: the points do not close a loop. "
            "A track file is a closed centre line: add the points of the missing stretch, or "
            "end the file near its first point"
        )


def check_lane_width(
    w_right_m: np.ndarray,
    w_left_m: np.ndarray,
    car_width_m: float,
    row: RowName,
    narrowing: Narrowing | None = None,
) -> None:
    """The lane must be wider than the car everywhere (``narrowing``: where the loader
    narrowed it, which the message then names as the cause)."""
    width = w_right_m + w_left_m
    narrow = np.flatnonzero(width <= car_width_m)
    if narrow.size:
        i = int(narrow[0])
        cause = ""
        if narrowing is not None and i in narrowing.indices:
            cause = (
                " after narrowing it where a turn is tighter than the half width or another leg "
                "of the track comes closer than the lane is wide (strict=True names the fold or "
                "crossing)"
            )
        raise TrackError(
            f"{row(i)}: lane is {width[i]:.3f} m wide{cause}, narrower than the car "
            f"({car_width_m:.3f} m)"
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


#: Least gap between the boundaries of two legs of the track that come closer than their
#: lane is wide (the straights of a hairpin side by side), where the loader clips them (m).
LEG_GAP_M = 0.1
#: Two points of the centre line ``d`` apart lie on different legs when the track between
#: them is longer than this many times ``d`` (the ends of a half circle: 1.57, one leg).
OTHER_LEG_ARC_RATIO = 2.0
#: Rows of the pairwise leg distances computed at once (bounds the memory to a few MB).
_LEG_CHUNK = 256


@dataclass(frozen=True)
class Narrowing:
    """Where the loader narrowed the lane: how many points (``indices`` into the track's
    points), by how much at most (both sides together)."""

    points: int = 0
    max_m: float = 0.0
    indices: tuple[int, ...] = ()

    @classmethod
    def between(
        cls,
        w_right_m: np.ndarray,
        w_left_m: np.ndarray,
        new_right_m: np.ndarray,
        new_left_m: np.ndarray,
    ) -> Narrowing:
        """What changed from the given half widths to the narrowed ones."""
        cut = (w_left_m - new_left_m) + (w_right_m - new_right_m)
        narrowed = np.flatnonzero(cut > 0.0)
        return cls(len(narrowed), float(cut.max(initial=0.0)), tuple(narrowed.tolist()))


#: Nothing narrowed.
NOT_NARROWED = Narrowing()


def arc_distance(from_s_m: np.ndarray, to_s_m: np.ndarray, length_m: float) -> np.ndarray:
    """Distances along the closed centre line from each arc length of ``from_s_m`` (rows)
    to each of ``to_s_m`` (columns)."""
    gap = np.abs(from_s_m[:, None] - to_s_m[None, :])
    return np.minimum(gap, length_m - gap)


def capped(
    width: np.ndarray, limit: np.ndarray, binding: np.ndarray, distance: np.ndarray
) -> np.ndarray:
    """``width`` lowered to ``limit`` at the ``binding`` points and, around them, to a cap
    that widens again at :data:`NARROWING_SLOPE` along the centre line (``distance``: the
    points' :func:`arc_distance`)."""
    binding = np.flatnonzero(binding)
    if not binding.size:
        return width
    cap = np.min(limit[binding][None, :] + NARROWING_SLOPE * distance[:, binding], axis=1)
    return np.minimum(width, cap)


def point_limits(sample_limit: np.ndarray, segment: np.ndarray, count: int) -> np.ndarray:
    """Each point's tightest limit over the samples of the two segments it bounds (widths
    are linear between points, so a segment within its ends' limits stays within them)."""
    tightest = np.full(count, np.inf)
    np.minimum.at(tightest, segment, sample_limit)
    return np.minimum(tightest, np.roll(tightest, 1))


def narrow_folding_widths(
    curvature_radpm: np.ndarray,
    segment: np.ndarray,
    distance: np.ndarray,
    w_right_m: np.ndarray,
    w_left_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Narrow each turn's inner half width to ``radius - FOLD_MARGIN_M`` where it is wider.

    Real circuits given with one fixed lane width (the F1TENTH collection's 2.2 m) have a
    few turns tighter than the half width: there the inner boundary would fold over itself.
    ``curvature_radpm`` is sampled densely along the centerline, ``segment`` says between
    which two input points each sample lies (``i``: points ``i`` and ``i + 1``, wrapping),
    ``distance`` is the points' :func:`arc_distance`. Each point's width is capped by the
    tightest turn of the two segments it bounds, and the cap widens again at
    ``NARROWING_SLOPE`` on either side: the smallest change that keeps the boundaries from
    folding or crossing, with a margin. Outer boundaries and points away from a too-tight
    turn keep their widths.
    """
    count = len(w_right_m)

    def narrowed(width: np.ndarray, curvature_toward_side: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", over="ignore"):  # a straight: an endless radius
            radius = point_limits(1.0 / np.maximum(curvature_toward_side, 0.0), segment, count)
        limit = np.maximum(radius - FOLD_MARGIN_M, 0.0)
        return capped(width, limit, width > radius, distance)

    return narrowed(w_right_m, -curvature_radpm), narrowed(w_left_m, curvature_radpm)


def meeting_leg_limits(
    position_m: np.ndarray, normal: np.ndarray, sample_s_m: np.ndarray, length_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The widest right and left half widths at centre-line samples that keep each boundary
    point nearer its own sample than any other leg's centre line, by :data:`LEG_GAP_M`.

    A boundary point ``q = p + w n`` (``n`` towards the side) is at ``w`` from its sample
    ``p``; it stays ``LEG_GAP_M`` nearer than another leg's point ``c`` when
    ``|q - c| >= w + gap``, that is ``w <= (|p - c|^2 - gap^2) / (2 (gap + n . (c - p)))``
    wherever ``gap + n . (c - p) > 0``. Both legs keep to their side of the line halfway
    between them, so their boundaries cannot cross. ``inf`` where no other leg is near.
    """
    limits = np.full((2, len(sample_s_m)), np.inf)  # right, left
    gap = LEG_GAP_M
    for start in range(0, len(sample_s_m), _LEG_CHUNK):
        rows = slice(start, start + _LEG_CHUNK)
        offset = position_m[None, :, :] - position_m[rows, None, :]
        squared = np.einsum("ijk,ijk->ij", offset, offset)
        along = arc_distance(sample_s_m[rows], sample_s_m, length_m)
        other = along > OTHER_LEG_ARC_RATIO * np.sqrt(squared)
        toward_left = np.einsum("ijk,ik->ij", offset, normal[rows])
        for side, toward in enumerate((-toward_left, toward_left)):
            ahead = other & (gap + toward > 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                bound = np.where(ahead, (squared - gap**2) / (2.0 * (gap + toward)), np.inf)
            limits[side, rows] = np.maximum(bound.min(axis=1), 0.0)
    return limits[0], limits[1]


def clip_meeting_legs(
    right_limit_m: np.ndarray,
    left_limit_m: np.ndarray,
    segment: np.ndarray,
    distance: np.ndarray,
    w_right_m: np.ndarray,
    w_left_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Clip the half widths where two legs of the track come closer than their lanes are
    wide (Montreal's hairpin: straights 1.9 m apart, a 2.2 m lane), to the samples'
    :func:`meeting_leg_limits` (``segment``: the input segment each sample lies on), the cap
    widening again at ``NARROWING_SLOPE`` as in a narrowed turn."""
    count = len(w_right_m)
    clipped = []
    for width, sample_limit in ((w_right_m, right_limit_m), (w_left_m, left_limit_m)):
        limit = point_limits(sample_limit, segment, count)
        clipped.append(capped(width, limit, width > limit, distance))
    return clipped[0], clipped[1]


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
    """Whether segment p1-p2 crosses or touches each segment q1-q2: an end of one lying
    exactly on the other counts (a figure eight sampled right at its crossing)."""

    def orient(a, b, c):
        return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (
            c[..., 0] - a[..., 0]
        )

    def lies_on(a, b, c, orientation):
        """Whether ``c``, on the line through ``a`` and ``b`` where ``orientation`` is 0,
        lies between them."""
        within = [
            (np.minimum(a[..., k], b[..., k]) <= c[..., k])
            & (c[..., k] <= np.maximum(a[..., k], b[..., k]))
            for k in (0, 1)
        ]
        return (orientation == 0.0) & within[0] & within[1]

    d1 = orient(q1, q2, p1)
    d2 = orient(q1, q2, p2)
    d3 = orient(p1, p2, q1)
    d4 = orient(p1, p2, q2)
    crossing = (d1 * d2 < 0.0) & (d3 * d4 < 0.0)
    if not (d1 * d2 * d3 * d4 == 0.0).any():  # no end on the other's line: the usual case
        return crossing
    return crossing | (
        lies_on(q1, q2, p1, d1)
        | lies_on(q1, q2, p2, d2)
        | lies_on(p1, p2, q1, d3)
        | lies_on(p1, p2, q2, d4)
    )
