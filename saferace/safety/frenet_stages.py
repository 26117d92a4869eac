"""Where the stages of a plan lie along the map, compiled by numba.

The LTV MPC (:mod:`saferace.safety.ltv_mpc`) steps its stages along the centre line one
after another: each stage's stretch depends on the curvature where the previous one
ended. In Python the loop's spline evaluations took about 0.09 ms a plan; compiled, a few
microseconds.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from saferace.numba_cache import recompiled_when_changed
from saferace.track.path import piece_values

#: Below this stretch per stage the curvature is sampled at its start.
MIN_STAGE_LENGTH_M = 1e-3


@recompiled_when_changed(piece_values)
@njit(cache=True)
def _heading_and_curvature(
    pieces: np.ndarray, spacing_m: float, length_m: float, s_m: float
) -> tuple[float, float]:
    """The centre line's heading and signed curvature at ``s_m`` (its cubic ``pieces``, one
    per ``spacing_m``, as :attr:`~saferace.track.path.ClosedPath.piece_array`)."""
    _, _, dx, dy, ddx, ddy = piece_values(pieces, spacing_m, length_m, s_m)
    return math.atan2(dy, dx), (dx * ddy - dy * ddx) / (dx * dx + dy * dy) ** 1.5


@recompiled_when_changed(piece_values)
@njit(cache=True)
def stages_along_map(
    travels_m: np.ndarray,
    offsets_m: np.ndarray,
    s0_m: float,
    pieces: np.ndarray,
    spacing_m: float,
    length_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The arc length each stage starts at (and the last ends at), and the centre line's
    mean curvature over each stage's stretch: its heading change over the stretch divided
    by its length, the stretch being ``travels_m`` (``v cos e_psi - ...`` times the
    stage's time) over ``1 - kappa e_y`` at the curvature where the stage starts
    (``offsets_m``: each stage's ``e_y``)."""
    stages = len(travels_m)
    s_stage = np.empty(stages + 1)
    kappas = np.empty(stages)
    s_m = s_stage[0] = s0_m
    for k in range(stages):
        heading, kappa = _heading_and_curvature(pieces, spacing_m, length_m, s_m)
        length = travels_m[k] / (1.0 - kappa * offsets_m[k])
        if length >= MIN_STAGE_LENGTH_M:
            ahead, _ = _heading_and_curvature(pieces, spacing_m, length_m, s_m + length)
            turn = (ahead - heading + math.pi) % (2.0 * math.pi) - math.pi
            kappa = turn / length
        kappas[k] = kappa
        s_m = s_stage[k + 1] = s_m + travels_m[k] / (1.0 - kappa * offsets_m[k])
    return s_stage, kappas
