"""The filter's fallback when it cannot trust its state: slow to a speed the interval fits at.

When the out-of-distribution monitor raises, or no control keeps every state of the
calibrated interval inside the lane, the lane constraints cannot be trusted to hold the car.
What still holds is physics: a car heading for an edge at ``v sin(e_psi)`` can turn away
within a lateral margin ``m`` if ``(v sin e_psi)^2 <= 2 a m`` at a lateral acceleration
``a`` its tyres can give. The fallback takes the worst of the interval (the smallest margin
to either edge, the largest heading error) and brakes towards the speed that satisfies this,
no lower than a creep speed (below which the steering barely acts); where even the interval's
offsets do not fit inside the lane, or the monitor says the interval itself is in doubt,
towards a controlled stop. Its steering is its own (:func:`fallback_steer_rad`), not the
agent's.
"""

from __future__ import annotations

import math

import numpy as np

from saferace.safety.models import MIN_SPEED_MPS

#: Braking where the filter's QP failed (m/s^2): firm but far inside the tyres' grip.
FALLBACK_BRAKE_MPS2 = 2.0
#: Braking where the state cannot be trusted (m/s^2): harder, since the car must slow
#: before an error it cannot see takes it out; the car brakes at up to 4, and the rest of
#: the tyres' grip is left for steering.
DISTRUST_BRAKE_MPS2 = 3.0
#: Steering of a fallback towards the centre line, besides the lane's curvature.
FALLBACK_STEER_PER_M = 1.0  # rad of steering per m of lateral offset
FALLBACK_STEER_PER_RAD = 1.0  # rad of steering per rad of heading error
#: Lateral acceleration the fallback counts on to turn away from an edge (m/s^2).
FALLBACK_LATERAL_MPS2 = 4.0
#: Heading errors below this (rad) count as this: a car square to its lane still drifts.
MIN_HEADING_RAD = 0.05


def interval_margin_m(
    lower: np.ndarray, upper: np.ndarray, w_left_m: float, w_right_m: float, half_width_m: float
) -> float:
    """The lane barrier at the interval's worst offset: negative where some offset in the
    interval puts the car outside."""
    return min(w_left_m - float(upper[0]), w_right_m + float(lower[0])) - half_width_m


def fitting_speed_mps(
    lower: np.ndarray,
    upper: np.ndarray,
    w_left_m: float,
    w_right_m: float,
    half_width_m: float,
    creep_speed_mps: float,
    lateral_mps2: float = FALLBACK_LATERAL_MPS2,
) -> float:
    """The speed the fallback slows to: ``sqrt(2 a m) / sin|e_psi|`` at the interval's worst
    margin ``m`` and heading, at least ``creep_speed_mps``; 0 (stop) where ``m < 0``."""
    margin = interval_margin_m(lower, upper, w_left_m, w_right_m, half_width_m)
    if margin < 0.0:
        return 0.0
    heading = max(abs(float(lower[1])), abs(float(upper[1])), MIN_HEADING_RAD)
    speed = math.sqrt(2.0 * lateral_mps2 * margin) / math.sin(min(heading, 0.5 * math.pi))
    return max(speed, creep_speed_mps)


def fallback_accel_bounds(
    v_x_mps: float, target_mps: float, control_dt_s: float
) -> tuple[float, float]:
    """``(lower, upper)`` of the acceleration that moves the speed towards ``target_mps``:
    braking at ``DISTRUST_BRAKE_MPS2`` from above it (less where that would pass a
    standstill), and from below, as much as the agent asks or accelerating no faster than
    reaching it within a step."""
    gap = (target_mps - v_x_mps) / control_dt_s
    if gap < 0.0:
        brake = max(gap, -DISTRUST_BRAKE_MPS2, -max(v_x_mps, 0.0) / control_dt_s)
        return brake, brake
    return -DISTRUST_BRAKE_MPS2, gap


def grip_steer_rad(v_x_mps: float, lateral_mps2: float, wheelbase_m: float) -> float:
    """The steering at which ``v_x^2 tan(delta) / L`` reaches ``lateral_mps2``."""
    return math.atan(lateral_mps2 * wheelbase_m / max(v_x_mps, MIN_SPEED_MPS) ** 2)


def towards_speed(
    box: tuple[np.ndarray, np.ndarray],
    v_x_mps: float,
    target_mps: float,
    control_dt_s: float,
    limit_accel_mps2: float | None,
    steer_max_rad: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The action ``box`` of a fallback step: its acceleration moving the speed towards
    ``target_mps`` (:func:`fallback_accel_bounds`) and never above ``limit_accel_mps2`` (the
    map's speed limit's row), its steering within ``+-steer_max_rad``."""
    lower, upper = box[0].copy(), box[1].copy()
    accel_low, accel_high = fallback_accel_bounds(v_x_mps, target_mps, control_dt_s)
    upper[1] = min(upper[1], accel_high)
    if limit_accel_mps2 is not None:
        upper[1] = max(min(upper[1], limit_accel_mps2), lower[1])
    lower[1] = min(max(lower[1], accel_low), upper[1])
    lower[0], upper[0] = max(lower[0], -steer_max_rad), min(upper[0], steer_max_rad)
    return lower, upper


def fallback_steer_rad(feedforward_rad: float, believed: np.ndarray | None) -> float:
    """The fallback's steering, whatever the agent asks: the lane's curvature from the map
    (``feedforward_rad``, which keeps the car's heading relative to the lane) and, where the
    ``believed`` ``[e_y, e_psi]`` can still be trusted (None: it cannot, after an alarm), a
    pull towards the centre line. The agent's own steering, kept within the barriers of the
    interval's centre, let a drifting agent out while the interval lagged its heading."""
    if believed is None:
        return feedforward_rad
    return (
        feedforward_rad - FALLBACK_STEER_PER_M * believed[0] - FALLBACK_STEER_PER_RAD * believed[1]
    )
