"""The speed limit of the filter's speed barrier: the reference's profile, braked for in time.

The task's reference speed profile (planned for 5 m/s^2 of lateral acceleration), scaled
by ``factor``, bounds the speed in each corner. Ahead of a slower stretch the limit falls
no faster than a friction ellipse allows: ``decel_mps2`` on a straight, less where the
limit already turns with ``v^2 kappa`` of the ellipse's ``lateral_mps2``. So a car held
below it has braked before it turns in, and does not brake hard while it turns (braking
in a corner near the grip limit spins this car: its rear brakes take 40% of the braking).
"""

from __future__ import annotations

import math

import numpy as np

from saferace.track.periodic import PeriodicInterpolator
from saferace.track.raceline import ReferenceLine


def braking_speed_limit(
    reference: ReferenceLine, factor: float, decel_mps2: float, lateral_mps2: float
) -> PeriodicInterpolator:
    """``v_limit(s)`` on the centerline's arc length: ``v^2 <= (factor v_ref)^2`` everywhere
    ahead, less ``2 decel sqrt(1 - (v^2 kappa / lateral)^2)`` per metre to it (a backward
    pass, twice round the closed track; ``kappa`` is the reference line's curvature).
    """
    if min(factor, decel_mps2, lateral_mps2) <= 0.0:
        raise ValueError(
            "factor, decel_mps2 and lateral_mps2 must be positive, "
            f"got {factor}, {decel_mps2}, {lateral_mps2}"
        )
    s = np.asarray(reference.center_s_m, dtype=float)
    limit_sq = ((factor * np.asarray(reference.center_vx_mps, dtype=float)) ** 2).tolist()
    curvature = np.abs(np.asarray(reference.center_kappa_radpm, dtype=float)).tolist()
    gaps = np.diff(np.append(s, s[0] + reference.track_length_m)).tolist()
    count = len(s)
    for k in range(2 * count, 0, -1):
        i = (k - 1) % count
        j = k % count
        grip_used = min(1.0, limit_sq[j] * curvature[j] / lateral_mps2)
        reachable = limit_sq[j] + 2.0 * decel_mps2 * math.sqrt(1.0 - grip_used**2) * gaps[i]
        limit_sq[i] = min(limit_sq[i], reachable)
    return PeriodicInterpolator(s, np.sqrt(limit_sq), reference.track_length_m)
