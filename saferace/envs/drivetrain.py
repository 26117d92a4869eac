"""The rc10's actuators: Ackermann steering servos and a rear-wheel-drive motor.

The task's action is physical: a front-wheel (bicycle) steering angle and a
longitudinal acceleration command. This module turns them into the MuJoCo
actuators' controls: a rate-limited steering target split into left/right wheel
angles by Ackermann geometry, and wheel torques from a feed-forward of the car's
mass and rolling losses: rear-wheel drive saturated by a DC motor's torque-speed
line, and braking on all four wheels.
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
    brake_torque_nm: float = 0.5  # per wheel
    front_brake_share: float = 0.6
    max_accel_mps2: float = 4.0
    max_brake_mps2: float = 4.0

    @property
    def top_speed_mps(self) -> float:
        """Where the motor's torque reaches zero: no speed above it is driven."""
        return self.motor_free_speed_radps * self.wheel_radius_m

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


def bicycle_angle(left_rad: float, right_rad: float) -> float:
    """The bicycle angle of two front-wheel angles: ``tan`` of it is the harmonic mean of
    theirs (the inverse of :func:`ackermann_angles`; their mean while they point apart)."""
    tan_left, tan_right = math.tan(left_rad), math.tan(right_rad)
    if tan_left * tan_right <= 0.0:
        return 0.5 * (left_rad + right_rad)
    return math.atan(2.0 * tan_left * tan_right / (tan_left + tan_right))


def rate_limited(target: float, current: float, max_rate: float, dt_s: float) -> float:
    """``target`` approached from ``current`` at no more than ``max_rate`` per second."""
    step = max_rate * dt_s
    return current + max(-step, min(step, target - current))


@dataclass(frozen=True)
class WheelTorques:
    """Torque per wheel, N m: the rear motors drive and brake, the front wheels only brake."""

    front_nm: float
    rear_nm: float


def wheel_torques(
    accel_mps2: float, speed_mps: float, rear_wheel_speed_radps: float, params: DrivetrainParams
) -> WheelTorques:
    """Wheel torques for an acceleration command, within the motor's and brakes' limits.

    Feed-forward ``(m_eff a + rolling losses) r``. Driving torque goes to the rear wheels,
    capped by the motor's torque-speed line ``T_stall (1 - omega / omega_free)``. Braking
    while rolling forward is shared by all four wheels (``front_brake_share`` on the front
    axle), as the rear axle alone cannot brake at 4 m/s^2 and still hold the road.
    """
    losses_n = 4.0 * params.wheel_damping_nms * speed_mps / params.wheel_radius_m**2
    total = (params.effective_mass_kg * accel_mps2 + losses_n) * params.wheel_radius_m
    if total < 0.0 and speed_mps > 0.05:
        limit = params.brake_torque_nm
        front = max(-limit, 0.5 * params.front_brake_share * total)
        rear = max(-limit, 0.5 * (1.0 - params.front_brake_share) * total)
        return WheelTorques(front_nm=front, rear_nm=rear)
    drive_limit = params.motor_stall_torque_nm * max(
        0.0, 1.0 - abs(rear_wheel_speed_radps) / params.motor_free_speed_radps
    )
    return WheelTorques(front_nm=0.0, rear_nm=max(-drive_limit, min(drive_limit, 0.5 * total)))
