"""Smoothing a noisy centre line with a regression spline, the lane's boundaries kept in place.

Real circuits are traced from maps or GPS, and the noise of those points is curvature the car
would have to steer: a periodic smoothing spline (scipy's ``splprep``, as TUM's track
preparation does) passes within ``rms_m`` of the points in the root-mean-square sense. Each
new centre point is then given the widths that keep the given boundaries where they were:
moved a distance ``d`` to the left, its left width shrinks by ``d`` and its right one grows
by ``d``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import splev, splprep
from scipy.spatial import cKDTree

from saferace.errors import TrackError
from saferace.track.path import ClosedPath

#: Spacing of the given centre line's samples that the new points are projected on.
_PROJECTION_STEP_M = 0.005


@dataclass(frozen=True)
class Smoothing:
    """What smoothing did: the tolerance asked for and how far the centre line moved."""

    rms_m: float
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
    x_m: np.ndarray, y_m: np.ndarray, w_right_m: np.ndarray, w_left_m: np.ndarray, rms_m: float
) -> SmoothedLane:
    """A periodic cubic smoothing spline within ``rms_m`` (RMS) of the closed centre line's
    points, sampled at as many points, evenly in its parameter; boundaries kept in place."""
    if not rms_m > 0.0:
        raise TrackError(f"the smoothing tolerance must be positive, got {rms_m} m")
    points = np.column_stack([x_m, y_m])
    closed = np.vstack([points, points[:1]])
    spline, _ = splprep(closed.T, s=len(points) * rms_m**2, per=1, k=3)
    x_new, y_new = splev(np.linspace(0.0, 1.0, len(points), endpoint=False), spline)
    given = ClosedPath(points)
    s = given.sample(min(_PROJECTION_STEP_M, given.length_m / len(points)))
    _, nearest = cKDTree(given.position(s)).query(np.column_stack([x_new, y_new]))
    s_nearest = s[nearest]
    shift = np.column_stack([x_new, y_new]) - given.position(s_nearest)
    left_shift_m = np.einsum("ij,ij->i", shift, given.normal(s_nearest))
    point_s = given.point_s_m
    period = given.length_m
    w_right = np.interp(s_nearest, point_s, w_right_m, period=period) + left_shift_m
    w_left = np.interp(s_nearest, point_s, w_left_m, period=period) - left_shift_m
    distance = np.hypot(shift[:, 0], shift[:, 1])
    smoothing = Smoothing(
        rms_m=float(rms_m),
        max_shift_m=float(distance.max()),
        rms_shift_m=float(np.sqrt(np.mean(distance**2))),
    )
    return SmoothedLane(np.asarray(x_new), np.asarray(y_new), w_right, w_left, smoothing)
