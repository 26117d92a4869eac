"""Steering geometry and the acceleration-to-torque map of the rc10."""

from __future__ import annotations

import math

import pytest

from saferace.envs.drivetrain import DrivetrainParams, ackermann_angles, rate_limited, wheel_torques

PARAMS = DrivetrainParams()


@pytest.mark.parametrize("steer", [0.05, 0.2, 0.36, -0.1, -0.3])
def test_ackermann_wheels_share_one_turn_centre(steer: float):
    left, right = ackermann_angles(steer, PARAMS)
    inner, outer = (left, right) if steer > 0 else (right, left)
    assert abs(inner) > abs(steer) > abs(outer)
    radius = PARAMS.wheelbase_m / math.tan(steer)
    half = PARAMS.track_width_m / 2
    # Each front wheel's axis passes through the turn centre (0, radius) in the rear-axle frame.
    assert PARAMS.wheelbase_m / math.tan(left) == pytest.approx(radius - half)
    assert PARAMS.wheelbase_m / math.tan(right) == pytest.approx(radius + half)


def test_straight_ahead_is_zero():
    assert ackermann_angles(0.0, PARAMS) == (0.0, 0.0)


def test_rate_limit():
    assert rate_limited(0.3, 0.0, 6.0, 0.05) == pytest.approx(0.3)
    assert rate_limited(0.36, -0.2, 6.0, 0.05) == pytest.approx(0.1)
    assert rate_limited(-0.36, 0.2, 6.0, 0.05) == pytest.approx(-0.1)


def test_drive_torque_is_rear_only_and_falls_with_wheel_speed():
    slow = wheel_torques(4.0, 0.5, 10.0, PARAMS)
    fast = wheel_torques(4.0, 7.0, 140.0, PARAMS)
    assert slow.front_nm == 0.0 and fast.front_nm == 0.0
    # F = m a + the four wheels' damping at v (torque d v / r each, as a force / r), shared
    # by the two rear wheels, times the wheel radius
    damping_force = 4 * PARAMS.wheel_damping_nms * 0.5 / PARAMS.wheel_radius_m**2
    force = PARAMS.effective_mass_kg * 4.0 + damping_force
    assert slow.rear_nm == pytest.approx(force * PARAMS.wheel_radius_m / 2)
    # at 140 rad/s the motor has lost 140/150 of its stall torque
    free_share = 1 - 140.0 / PARAMS.motor_free_speed_radps
    assert fast.rear_nm == pytest.approx(PARAMS.motor_stall_torque_nm * free_share)


def test_braking_uses_all_wheels_with_front_bias():
    torques = wheel_torques(-3.0, 5.0, 100.0, PARAMS)
    assert torques.front_nm < torques.rear_nm < 0.0
    assert torques.front_nm / torques.rear_nm == pytest.approx(0.6 / 0.4)
    total_force = 2 * (torques.front_nm + torques.rear_nm) / PARAMS.wheel_radius_m
    losses = 4 * PARAMS.wheel_damping_nms * 5.0 / PARAMS.wheel_radius_m**2
    assert total_force == pytest.approx(PARAMS.effective_mass_kg * -3.0 + losses)


def test_reversing_from_rest_uses_the_motor():
    torques = wheel_torques(-2.0, 0.0, 0.0, PARAMS)
    assert torques.front_nm == 0.0 and torques.rear_nm < 0.0
