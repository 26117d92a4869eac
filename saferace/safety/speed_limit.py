"""The speed limit of the filter's speed barrier: the reference's profile, braked for in time.

The task's reference speed profile (planned for 5 m/s^2 of lateral acceleration), scaled
by ``factor``, bounds the speed in each corner. Before a corner the limit falls no faster
than ``decel_mps2`` allows, so a car held below it reaches the corner slow enough without
braking hard while it turns (braking in a corner at the grip limit spins this car: its
rear brakes take 40% of the braking).
"""

from __future__ import annotations

import numpy as np

from saferace.track.periodic import PeriodicInterpolator
from saferace.track.raceline import ReferenceLine


def braking_speed_limit(
    reference: ReferenceLine, factor: float, decel_mps2: float
) -> PeriodicInterpolator:
    """``v_limit(s)`` on the centerline's arc length: ``v^2 <= (factor v_ref)^2`` everywhere
    ahead, less ``2 decel`` per metre to it (a backward pass, twice round the closed track).
    """
    if factor <= 0.0 or decel_mps2 <= 0.0:
        raise ValueError(f"factor and decel_mps2 must be positive, got {factor}, {decel_mps2}")
    s = np.asarray(reference.center_s_m, dtype=float)
    limit_sq = (factor * np.asarray(reference.center_vx_mps, dtype=float)) ** 2
    gaps = np.diff(np.append(s, s[0] + reference.track_length_m))
    count = len(s)
    for k in range(2 * count, 0, -1):
        i = (k - 1) % count
        j = k % count
        limit_sq[i] = min(limit_sq[i], limit_sq[j] + 2.0 * decel_mps2 * gaps[i])
    return PeriodicInterpolator(s, np.sqrt(limit_sq), reference.track_length_m)
