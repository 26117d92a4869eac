"""Closed planar curves parameterised by arc length.

A :class:`ClosedPath` fits a periodic cubic spline through the given points,
re-samples it densely at equal arc-length steps and fits a second periodic
spline against arc length, so that the parameter *is* the arc length ``s``
(to about 1e-6 relative). Vectorised evaluation goes through scipy; the scalar
methods used on the per-step hot path evaluate the cubic pieces directly
(:func:`piece_values`, compiled by numba, which compiled code such as a plan's
stages calls too), an order of magnitude faster than calling scipy for a single
point.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy.interpolate import CubicSpline

#: Knot spacing of the arc-length spline. Fine enough that re-sampling changes
#: the curve by well under a micrometre on 1/10-scale tracks.
KNOT_SPACING_M = 0.02
_DENSE_SAMPLES_PER_SEGMENT = 64


class ClosedPath:
    """A closed C2 curve through ``points`` (shape (n, 2)), parameterised by arc length.

    The last point may repeat the first; it is dropped. ``knot_spacing_m`` sets the
    arc-length spline's resolution.
    """

    def __init__(self, points: np.ndarray, knot_spacing_m: float = KNOT_SPACING_M) -> None:
        points = np.asarray(points, dtype=float)
        if np.allclose(points[0], points[-1]):
            points = points[:-1]
        chord_spline, chord_params = _chord_spline(points)
        dense_t, dense_s = _arc_length_table(chord_spline, chord_params)
        self.length_m = float(dense_s[-1])
        self.point_s_m = np.interp(chord_params[:-1], dense_t, dense_s)
        knot_count = max(len(points), math.ceil(self.length_m / knot_spacing_m))
        self.knot_s_m = np.linspace(0.0, self.length_m, knot_count + 1)
        knot_xy = chord_spline(np.interp(self.knot_s_m, dense_s, dense_t))
        knot_xy[-1] = knot_xy[0]
        self._spline = CubicSpline(self.knot_s_m, knot_xy, bc_type="periodic")
        self.knot_spacing_m = self.length_m / knot_count
        self.piece_count = knot_count
        self.knot_xy = knot_xy[:-1]
        # Per-piece cubic coefficients (ax, bx, cx, dx, ay, by, cy, dy) with
        # x = ((ax t + bx) t + cx) t + dx: an array for compiled code, Python floats for
        # the Frenet projection's inline Newton steps.
        self.piece_array = np.ascontiguousarray(
            np.concatenate([self._spline.c[:, :, 0].T, self._spline.c[:, :, 1].T], axis=1)
        )
        self.pieces = [tuple(float(value) for value in piece) for piece in self.piece_array]

    # ---------------------------------------------------------------- vectorised
    def wrap(self, s: np.ndarray | float) -> np.ndarray | float:
        """Arc length wrapped into ``[0, length)``."""
        return np.mod(s, self.length_m)

    def position(self, s: np.ndarray | float) -> np.ndarray:
        """Points ``(..., 2)`` at arc length ``s``."""
        return self._spline(self.wrap(s))

    def tangent(self, s: np.ndarray | float) -> np.ndarray:
        """Unit tangents ``(..., 2)`` at ``s``."""
        d = self._spline(self.wrap(s), 1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def normal(self, s: np.ndarray | float) -> np.ndarray:
        """Unit normals ``(..., 2)`` pointing to the left of the direction of travel."""
        t = self.tangent(s)
        return np.stack([-t[..., 1], t[..., 0]], axis=-1)

    def heading(self, s: np.ndarray | float) -> np.ndarray:
        """Tangent direction in radians, in ``(-pi, pi]``."""
        d = self._spline(self.wrap(s), 1)
        return np.arctan2(d[..., 1], d[..., 0])

    def curvature(self, s: np.ndarray | float) -> np.ndarray:
        """Signed curvature in 1/m, positive when the path turns left."""
        s = self.wrap(s)
        d1 = self._spline(s, 1)
        d2 = self._spline(s, 2)
        cross = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
        return cross / np.linalg.norm(d1, axis=-1) ** 3

    def sample(self, step_m: float) -> np.ndarray:
        """About equally spaced arc lengths ``[0, length)`` with spacing close to ``step_m``."""
        count = max(10, round(self.length_m / step_m))
        return np.linspace(0.0, self.length_m, count, endpoint=False)

    def curvature_squared_integral(self, samples: int = 20000) -> float:
        """Integral of the squared curvature over one lap, in 1/m."""
        s = np.linspace(0.0, self.length_m, samples, endpoint=False)
        return float(np.sum(self.curvature(s) ** 2) * self.length_m / samples)

    def nearest_knot(self, x: float, y: float) -> float:
        """Arc length of the knot closest to ``(x, y)``: a global scan, for first guesses."""
        d2 = (self.knot_xy[:, 0] - x) ** 2 + (self.knot_xy[:, 1] - y) ** 2
        return float(self.knot_s_m[int(np.argmin(d2))])

    # ---------------------------------------------------------------- scalar, fast
    def eval_scalar(self, s: float) -> tuple[float, float, float, float, float, float]:
        """``(x, y, dx, dy, ddx, ddy)`` at arc length ``s`` (derivatives with respect to s)."""
        return piece_values(self.piece_array, self.knot_spacing_m, self.length_m, float(s))

    def curvature_scalar(self, s: float) -> float:
        """Signed curvature at one arc length, without numpy overhead (per-step use)."""
        return self.curvature_and_heading_scalar(s)[0]

    def heading_scalar(self, s: float) -> float:
        """:meth:`heading` at one arc length, without numpy overhead (per-step use)."""
        _, _, dx, dy, _, _ = self.eval_scalar(s)
        return math.atan2(dy, dx)

    def curvature_and_heading_scalar(self, s: float) -> tuple[float, float]:
        """Signed curvature and heading at one arc length from one evaluation."""
        _, _, dx, dy, ddx, ddy = self.eval_scalar(s)
        return (dx * ddy - dy * ddx) / (dx * dx + dy * dy) ** 1.5, math.atan2(dy, dx)


@njit(cache=True)
def piece_values(
    pieces: np.ndarray, spacing_m: float, length_m: float, s_m: float
) -> tuple[float, float, float, float, float, float]:
    """``(x, y, dx, dy, ddx, ddy)`` at arc length ``s_m`` of a closed path's cubic ``pieces``
    (:attr:`ClosedPath.piece_array`, one per ``spacing_m``), derivatives with respect to s."""
    s_m = s_m % length_m
    k = min(int(s_m / spacing_m), len(pieces) - 1)
    t = s_m - k * spacing_m
    ax, bx, cx, dx, ay, by, cy, dy = pieces[k]
    return (
        ((ax * t + bx) * t + cx) * t + dx,
        ((ay * t + by) * t + cy) * t + dy,
        (3.0 * ax * t + 2.0 * bx) * t + cx,
        (3.0 * ay * t + 2.0 * by) * t + cy,
        6.0 * ax * t + 2.0 * bx,
        6.0 * ay * t + 2.0 * by,
    )


def _chord_spline(points: np.ndarray) -> tuple[CubicSpline, np.ndarray]:
    """Periodic spline through ``points`` parameterised by cumulative chord length."""
    closed = np.vstack([points, points[:1]])
    chords = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    params = np.concatenate([[0.0], np.cumsum(chords)])
    return CubicSpline(params, closed, bc_type="periodic"), params


def _arc_length_table(spline: CubicSpline, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dense table of spline parameter against arc length (Simpson's rule per sub-step)."""
    fractions = np.linspace(0.0, 1.0, _DENSE_SAMPLES_PER_SEGMENT, endpoint=False)
    starts, widths = params[:-1], np.diff(params)
    t = (starts[:, None] + widths[:, None] * fractions[None, :]).ravel()
    t = np.append(t, params[-1])
    mid = 0.5 * (t[:-1] + t[1:])
    speed = lambda u: np.linalg.norm(spline(u, 1), axis=-1)  # noqa: E731
    steps = np.diff(t) / 6.0 * (speed(t[:-1]) + 4.0 * speed(mid) + speed(t[1:]))
    return t, np.concatenate([[0.0], np.cumsum(steps)])
