"""The rc10's actuators: Ackermann steering servos and a rear-wheel-drive motor.

The task's action is physical: a front-wheel (bicycle) steering angle and a
longitudinal acceleration command. This module turns them into the MuJoCo
actuators' controls: a rate-limited steering target split into left/right wheel
angles by Ackermann geometry, and rear-wheel torques from a feed-forward of the
car's mass and rolling losses, saturated by a DC motor's torque-speed line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class DrivetrainParams:
    """Geometry and actuator limits of the rc10 (sources in assets/vehicles/rc10/README.md)."""

    wheelbase_m: float = 0.33
    track_width_m: float = 0.28
    wheel_radius_m: float = 0.05
    mass_kg: float = 3.5
    wheel_spin_inertia_kgm2: float = 1.7e-4  # 0.12 kg sphere (0.00012) + armature 0.00005
    wheel_damping_nms: float = 1e-4
    max_steer_rad: float = 0.36
    max_steer_rate_radps: float = 6.0
    motor_stall_torque_nm: float = 0.5  # per rear wheel
    motor_free_speed_radps: float = 150.0  # wheel speed at which the motor's torque reaches zero
    max_accel_mps2: float = 4.0
    max_brake_mps2: float = 4.0

    @property
    def effective_mass_kg(self) -> float:
        """Mass plus the four wheels' spin inertia seen at the contact patch."""
        return self.mass_kg + 4.0 * self.wheel_spin_inertia_kgm2 / self.wheel_radius_m**2


def ackermann_angles(steer_rad: float, params: DrivetrainParams) -> tuple[float, float]:
    """Left and right front-wheel angles that share one turn centre with the bicycle angle."""
    if abs(steer_rad) < 1e-9:
        return 0.0, 0.0
    radius = params.wheelbase_m / math.tan(steer_rad)  # signed: positive turns left
    half_track = 0.5 * params.track_width_m
    left = math.atan(params.wheelbase_m / (radius - half_track))
    right = math.atan(params.wheelbase_m / (radius + half_track))
    return left, right


def rate_limited(target: float, current: float, max_rate: float, dt_s: float) -> float:
    """``target`` approached from ``current`` at no more than ``max_rate`` per second."""
    step = max_rate * dt_s
    return current + max(-step, min(step, target - current))


def rear_wheel_torque(
    accel_mps2: float, speed_mps: float, wheel_speed_radps: float, params: DrivetrainParams
) -> float:
    """Torque per rear wheel for an acceleration command, within the motor's limits.

    Feed-forward ``(m_eff a + rolling losses) r / 2``; driving torque is capped by the
    torque-speed line ``T_stall (1 - omega / omega_free)``, braking torque by ``T_stall``.
    """
    losses_n = 4.0 * params.wheel_damping_nms * speed_mps / params.wheel_radius_m**2
    torque = (params.effective_mass_kg * accel_mps2 + losses_n) * params.wheel_radius_m / 2.0
    drive_limit = params.motor_stall_torque_nm * max(
        0.0, 1.0 - abs(wheel_speed_radps) / params.motor_free_speed_radps
    )
    if torque * (wheel_speed_radps if abs(wheel_speed_radps) > 1e-6 else 1.0) >= 0.0:
        return max(-drive_limit, min(drive_limit, torque))
    return max(-params.motor_stall_torque_nm, min(params.motor_stall_torque_nm, torque))
