"""The speed profile asks only for what the simulated car can do: its acceleration falls
with speed as the motor's torque does."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from test_mpc import stadium

import saferace  # noqa: F401  - registers the tasks
from saferace.envs.drivetrain import DrivetrainParams
from saferace.track import VehicleEnvelope
from saferace.track.speed_profile import speed_profile

START_MPS, STEP_M = 1.0, 0.1


def test_the_envelope_is_the_drivetrains_motor_line():
    params, envelope = DrivetrainParams(), VehicleEnvelope()
    stall_force_n = 2.0 * params.motor_stall_torque_nm / params.wheel_radius_m
    assert envelope.drive_accel_at_rest_mps2 == pytest.approx(
        stall_force_n / params.effective_mass_kg, rel=0.01
    )
    free_speed = params.motor_free_speed_radps * params.wheel_radius_m
    assert envelope.drive_free_speed_mps == pytest.approx(free_speed)
    losses = 4.0 * params.wheel_damping_nms / params.wheel_radius_m**2 / params.effective_mass_kg
    assert envelope.rolling_decel_per_s == pytest.approx(losses, rel=0.02)
    assert envelope.drive_accel_mps2(0.0) == envelope.a_accel_max_mps2
    assert envelope.drive_accel_mps2(5.0) < 2.0 and envelope.drive_accel_mps2(7.2) == 0.0


def test_the_profile_speeds_up_along_a_straight_as_the_car_does():
    envelope = VehicleEnvelope()
    kappa = np.zeros(1500)
    kappa[0] = envelope.a_lat_max_mps2 / START_MPS**2  # a corner taken at 1 m/s, then 150 m
    planned = speed_profile(kappa, STEP_M, envelope).vx_mps
    env = gym.make(
        "saferace/CenterLine-v0",
        track=stadium(straight_m=120.0, radius_m=20.0),
        image_size=(16, 16),
    )
    _, info = env.reset(seed=0, options={"start_s_m": 0.0, "start_speed_mps": START_MPS})
    distance, speed = [0.0], [START_MPS]
    while info["s_m"] < 100.0:
        _, _, _, _, info = env.step(np.array([0.0, envelope.a_accel_max_mps2]))
        distance.append(info["s_m"])
        speed.append(info["v_x_mps"])
    env.close()
    for s_m in (2.0, 10.0, 25.0, 50.0, 90.0):
        driven = np.interp(s_m, distance, speed)
        assert planned[round(s_m / STEP_M)] == pytest.approx(driven, rel=0.04), s_m
