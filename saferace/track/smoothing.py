"""Smoothing a noisy centre line with a regression spline, the lane's boundaries kept in place.

Real circuits are traced from maps or GPS, and the noise of those points is curvature the car
would have to steer. The smoothed centre line is the cubic smoothing spline ``c(s)`` that
minimises ``sum_i |p_i - c(s_i)|^2 + lam * integral |c''(s)|^2 ds`` over the closed line's
points ``p_i`` at their chord-length positions ``s_i``: as ``s`` is close to arc length,
``|c''|^2`` is the curvature squared, so the spline trades the distance it moves the points
against exactly the ``integral kappa^2 ds`` the car steers (a penalised spline, as TUM's track
preparation smooths with a regression spline; FITPACK's ``splprep`` places few knots and left
0.3 m radii at the F1TENTH circuits' hairpins). ``lam`` is found so that the points move
``rms_m`` in the root-mean-square sense.

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
from typing import Literal

import numpy as np
from scipy.interpolate import make_smoothing_spline
from scipy.optimize import brentq
from scipy.spatial import cKDTree

from saferace.errors import TrackError
from saferace.track.path import ClosedPath

#: Spacing of the given centre line's samples that the new points are projected on.
_PROJECTION_STEP_M = 0.005
#: What a smoothed lane keeps of the given one.
SmoothingKeeps = Literal["widths", "boundaries"]
SMOOTHING_KEEPS: tuple[str, ...] = ("widths", "boundaries")
#: Range of log10(lam) searched, and the tolerance on it.
_LOG_LAM_RANGE = (-8.0, 8.0)
_LOG_LAM_TOL = 0.01


@dataclass(frozen=True)
class Smoothing:
    """What smoothing did: the tolerance asked for, what the lane kept and how far the centre
    line moved."""

    rms_m: float
    keeps: str
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
    """The curvature-penalised smoothing spline whose points lie ``rms_m`` (RMS) from the closed
    centre line's, one per given point, with the given widths or boundaries (``keeps``)."""
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
    """The closed line's points on the penalised spline whose RMS distance from them is
    ``rms_m``: the line is laid out three times along its chord length (so the middle lap's
    spline is periodic to rounding) and ``lam`` is found by Brent's method on ``log10(lam)``."""
    closed = np.vstack([points, points[:1]])
    chords = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(chords[:-1])])
    period = float(chords.sum())
    s_tiled = np.concatenate([s - period, s, s + period])
    points_tiled = np.vstack([points, points, points])

    def fitted(log_lam: float) -> np.ndarray:
        return make_smoothing_spline(s_tiled, points_tiled, lam=10.0**log_lam)(s)

    def excess_m(log_lam: float) -> float:
        return float(np.sqrt(np.mean(np.sum((fitted(log_lam) - points) ** 2, axis=1)))) - rms_m

    low, high = _LOG_LAM_RANGE
    if excess_m(high) < 0.0:
        raise TrackError(
            f"the smoothing tolerance {rms_m} m is more than the centre line's distance from "
            "a straight line: nothing of the track would be left"
        )
    if excess_m(low) > 0.0:
        return points.copy()
    return fitted(brentq(excess_m, low, high, xtol=_LOG_LAM_TOL))
