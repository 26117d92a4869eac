"""Smoothing a noisy centre line with a curvature-penalised regression spline.

Real circuits are traced from maps or GPS, and the noise of those points is curvature the car
would have to steer. The smoothed centre line is the cubic smoothing spline ``c(s)`` that
minimises ``sum_i w_i |p_i - c(s_i)|^2 + lam * integral |c''(s)|^2 ds`` over the closed
line's points ``p_i`` at their chord-length positions ``s_i`` (``w_i``: each point's share of
the lap): where ``s`` is close to arc length, ``|c''|^2`` is about the curvature squared, so
the spline trades the distance it moves the points against about the ``integral kappa^2 ds``
the car steers (a penalised spline, as TUM's track preparation smooths with a regression
spline; FITPACK's ``splprep``, used before, places few knots on a long lap and left 0.3 m
radii at the F1TENTH circuits' hairpins). ``lam`` is found so that the points move ``rms_m``
in the (weighted) root-mean-square sense, and the new points are spaced evenly along it.

What the lane keeps (``keeps``): ``"widths"`` (the default) gives each new centre point the
widths given at the nearest point of the old one, so the boundaries move with the centre line:
the lane of a circuit defined by its centre line and widths, as the F1TENTH collection's (a
fixed 2.2 m lane about a smoothed centre line, whose racing lines TUM's tools computed in that
lane) and TUM's track preparation. ``"boundaries"`` keeps the given boundaries where they were,
for lanes whose edges were measured: moved a distance ``d`` to the left, a point's left width
shrinks by ``d`` and its right one grows by ``d``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from scipy.interpolate import make_smoothing_spline
from scipy.optimize import brentq
from scipy.spatial import cKDTree

from saferace.errors import TrackError
from saferace.track.path import ClosedPath

#: Spacing of the given centre line's samples that the new points are projected on.
_PROJECTION_STEP_M = 0.005
#: What a smoothed lane keeps of the given one.
SmoothingKeeps = Literal["widths", "boundaries"]  # saferace.names.SMOOTHING_KEEPS
SMOOTHING_KEEPS: tuple[str, ...] = get_args(SmoothingKeeps)
#: Range of log10(lam / mean spacing^3) searched, and the tolerance on it.
_LOG_LAM_RANGE = (-6.0, 14.0)
_LOG_LAM_TOL = 0.01


@dataclass(frozen=True)
class Smoothing:
    """What smoothing did: the tolerance asked for, what the lane kept and how far the centre
    line moved."""

    rms_m: float
    keeps: SmoothingKeeps
    max_shift_m: float
    rms_shift_m: float


@dataclass(frozen=True)
class SmoothedLane:
    """The smoothed centre line (as many points as given) and the widths that keep the lane."""

    x_m: np.ndarray
    y_m: np.ndarray
    w_right_m: np.ndarray
    w_left_m: np.ndarray
    smoothing: Smoothing


def smooth_centerline(
    x_m: np.ndarray,
    y_m: np.ndarray,
    w_right_m: np.ndarray,
    w_left_m: np.ndarray,
    rms_m: float,
    keeps: SmoothingKeeps = "widths",
) -> SmoothedLane:
    """The curvature-penalised smoothing spline that moves the closed centre line
    by ``rms_m`` (RMS), as many points evenly spaced, with the given widths or boundaries
    (``keeps``)."""
    if not rms_m > 0.0:
        raise TrackError(f"the smoothing tolerance must be positive, got {rms_m} m")
    if keeps not in SMOOTHING_KEEPS:
        raise TrackError(f"a smoothed lane keeps one of {SMOOTHING_KEEPS}, got {keeps!r}")
    points = np.column_stack([x_m, y_m])
    smoothed = _penalised_fit(points, rms_m)
    given = ClosedPath(points)
    s = given.sample(min(_PROJECTION_STEP_M, given.length_m / len(points)))
    _, nearest = cKDTree(given.position(s)).query(smoothed)
    s_nearest = s[nearest]
    shift = smoothed - given.position(s_nearest)
    point_s = given.point_s_m
    period = given.length_m
    w_right = np.interp(s_nearest, point_s, w_right_m, period=period)
    w_left = np.interp(s_nearest, point_s, w_left_m, period=period)
    if keeps == "boundaries":
        left_shift_m = np.einsum("ij,ij->i", shift, given.normal(s_nearest))
        w_right, w_left = w_right + left_shift_m, w_left - left_shift_m
    distance = np.hypot(shift[:, 0], shift[:, 1])
    smoothing = Smoothing(
        rms_m=float(rms_m),
        keeps=keeps,
        max_shift_m=float(distance.max()),
        rms_shift_m=float(np.sqrt(np.mean(distance**2))),
    )
    return SmoothedLane(smoothed[:, 0], smoothed[:, 1], w_right, w_left, smoothing)


def _penalised_fit(points: np.ndarray, rms_m: float) -> np.ndarray:
    """As many points, evenly spaced along the closed line's penalised spline whose weighted
    RMS distance from the given points is ``rms_m``.

    Each point weighs its share of the lap (half its two chords), so a cluster of points counts
    as the stretch it covers. The line is laid out three times along its chord length, so the
    middle lap's spline is periodic to rounding. ``lam`` is scaled by the mean spacing cubed
    (the penalty's units against the residuals') and found by Brent's method on its logarithm.
    """
    closed = np.vstack([points, points[:1]])
    chords = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    if np.any(chords <= 0.0):
        raise TrackError(
            f"the centre line repeats point {int(np.argmin(chords))}: cannot smooth it"
        )
    s = np.concatenate([[0.0], np.cumsum(chords[:-1])])
    period = float(chords.sum())
    weights = 0.5 * (chords + np.roll(chords, 1))
    weights = weights / weights.mean()
    s_tiled = np.concatenate([s - period, s, s + period])
    weights_tiled = np.tile(weights, 3)
    lam_unit = (period / len(points)) ** 3

    def splines(log_lam: float) -> list:
        return [
            make_smoothing_spline(
                s_tiled, np.tile(points[:, axis], 3), w=weights_tiled, lam=lam_unit * 10.0**log_lam
            )
            for axis in (0, 1)
        ]

    def rms_moved_m(log_lam: float) -> float:
        moved_sq = sum(
            (spline(s) - points[:, axis]) ** 2 for axis, spline in enumerate(splines(log_lam))
        )
        return float(np.sqrt(np.sum(weights * moved_sq) / np.sum(weights)))

    low, high = _LOG_LAM_RANGE
    most, least = rms_moved_m(high), rms_moved_m(low)
    if not least <= rms_m <= most:
        raise TrackError(
            f"the smoothing tolerance {rms_m} m is outside what smoothing this centre line can "
            f"move it by ({least:.2g} to {most:.3g} m RMS)"
        )
    x_spline, y_spline = splines(
        brentq(lambda v: rms_moved_m(v) - rms_m, low, high, xtol=_LOG_LAM_TOL)
    )
    s_even = np.linspace(0.0, period, len(points), endpoint=False)
    return np.column_stack([x_spline(s_even), y_spline(s_even)])
