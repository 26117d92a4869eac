"""Forward-backward speed profile of a closed path under a friction ellipse.

Lateral acceleration ``v^2 |kappa|`` and longitudinal acceleration share the tyre's
grip: ``(a_x / a_x,max)^2 + (a_y / a_y,max)^2 <= 1`` (Heilmeier et al. 2019), where
speeding up ``a_x,max`` is what the motor can still push at that speed
(:meth:`~saferace.track.VehicleEnvelope.drive_accel_mps2`). The
profile starts at the slowest corner, where the speed is set by the lateral limit
alone, so one forward (accelerating) and one backward (braking) pass around the
loop give the periodic solution.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from saferace.track.vehicle_envelope import VehicleEnvelope


@dataclass(frozen=True)
class SpeedProfile:
    """Speed and acceleration at equally spaced samples of a closed path."""

    vx_mps: np.ndarray
    ax_mps2: np.ndarray
    lap_time_s: float


def speed_profile(
    kappa_radpm: np.ndarray, step_m: float, envelope: VehicleEnvelope
) -> SpeedProfile:
    """Fastest speed profile along samples ``step_m`` apart with curvature ``kappa_radpm``."""
    kappa = np.abs(np.asarray(kappa_radpm, dtype=float))
    count = len(kappa)
    with np.errstate(divide="ignore", over="ignore"):
        v_corner = np.sqrt(envelope.a_lat_max_mps2 / kappa)
    v_limit = np.minimum(v_corner, envelope.v_max_mps)
    start = int(np.argmin(v_limit))
    order = (start + np.arange(count + 1)) % count

    v = v_limit.copy()
    _pass(v, kappa, order, step_m, envelope.drive_accel_mps2, envelope.a_lat_max_mps2)
    brake = envelope.a_brake_max_mps2
    _pass(v, kappa, order[::-1], step_m, lambda _speed: brake, envelope.a_lat_max_mps2)

    v_next = np.roll(v, -1)
    ax = (v_next**2 - v**2) / (2.0 * step_m)
    lap_time = float(np.sum(2.0 * step_m / (v + v_next)))
    return SpeedProfile(vx_mps=v, ax_mps2=ax, lap_time_s=lap_time)


def _pass(
    v: np.ndarray,
    kappa: np.ndarray,
    order: np.ndarray,
    step_m: float,
    a_long_max: Callable[[float], float],
    a_lat_max: float,
) -> None:
    """One pass in ``order``: cap each speed by what the grip allows coming from the previous.

    ``a_long_max(speed)`` is the longitudinal limit at the start of each step (the motor's
    falls with speed). Speeds are only ever lowered, so the braking pass keeps what the
    accelerating pass set.
    """
    speeds = v.tolist()
    curvature = kappa.tolist()
    for prev, cur in zip(order[:-1].tolist(), order[1:].tolist(), strict=True):
        v_prev_sq = speeds[prev] * speeds[prev]
        a_long = a_long_max(speeds[prev])
        if a_long <= 0.0:
            speeds[cur] = min(speeds[cur], speeds[prev])
            continue
        reachable_sq = max_next_speed_squared(
            v_prev_sq, curvature[prev], curvature[cur], step_m, a_long, a_lat_max
        )
        if reachable_sq < speeds[cur] * speeds[cur]:
            speeds[cur] = math.sqrt(reachable_sq)
    v[:] = speeds


def max_next_speed_squared(
    v_prev_sq: float,
    kappa_prev: float,
    kappa_next: float,
    step_m: float,
    a_long_max: float,
    a_lat_max: float,
) -> float:
    """Largest ``v_next^2`` whose constant ``a_x`` fits the friction ellipse at both segment ends.

    With ``u = v^2`` and ``a_x = (u_next - u_prev) / (2 step)`` the condition at each end,
    ``(a_x / a_long)^2 + (u kappa / a_lat)^2 <= 1``, is an ellipse in ``u_next``: the start
    end bounds ``u_next`` directly, the far end through a quadratic. A pass only limits
    its own direction (speeding up, or braking when run backwards), so the result is
    never below ``v_prev^2``: where the far end needs a slower speed, its own lateral
    limit and the other pass take care of it.
    """
    reach = 2.0 * step_m * a_long_max
    start_use = min(1.0, v_prev_sq * kappa_prev / a_lat_max)
    bound_start = v_prev_sq + reach * math.sqrt(1.0 - start_use * start_use)
    k = kappa_next / a_lat_max
    quad_a = 1.0 / reach**2 + k * k
    quad_b = -2.0 * v_prev_sq / reach**2
    quad_c = v_prev_sq * v_prev_sq / reach**2 - 1.0
    discriminant = quad_b * quad_b - 4.0 * quad_a * quad_c
    if discriminant < 0.0:
        return v_prev_sq
    bound_end = (-quad_b + math.sqrt(discriminant)) / (2.0 * quad_a)
    return max(v_prev_sq, min(bound_start, bound_end))
