"""The expert MPC tracks a straight line and a circle with the model itself as the plant (behind
the steering servo's lag), and holds a straight at top speed in the simulator."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  - registers the tasks
from saferace.agents.mpc import MPCExpert, MPCSettings
from saferace.safety.models import FrenetModel
from saferace.safety.vehicle_params import VehicleParams
from saferace.track import Track
from saferace.track.raceline import center_line

PLANT_PARAMS = VehicleParams(
    cf0_npr=20.0, df_nspmr=180.0, cr0_npr=20.0, dr_nspmr=200.0, yaw_inertia_kgm2=0.085
)


def stadium(straight_m: float = 60.0, radius_m: float = 8.0) -> Track:
    length = 2 * straight_m + 2 * math.pi * radius_m
    s = np.linspace(0.0, length, 800, endpoint=False)
    points = []
    for u in s:
        if u < straight_m:
            points.append((u - straight_m / 2, -radius_m))
        elif u < straight_m + math.pi * radius_m:
            a = -math.pi / 2 + (u - straight_m) / radius_m
            points.append((straight_m / 2 + radius_m * math.cos(a), radius_m * math.sin(a)))
        elif u < 2 * straight_m + math.pi * radius_m:
            points.append((straight_m / 2 - (u - straight_m - math.pi * radius_m), radius_m))
        else:
            a = math.pi / 2 + (u - 2 * straight_m - math.pi * radius_m) / radius_m
            points.append((-straight_m / 2 + radius_m * math.cos(a), radius_m * math.sin(a)))
    x, y = np.array(points).T
    return Track.from_arrays(x, y, 0.6, 0.6, name="stadium")


def circle(radius_m: float = 4.0) -> Track:
    theta = np.linspace(0.0, 2 * math.pi, 300, endpoint=False)
    return Track.from_arrays(
        radius_m * np.cos(theta), radius_m * np.sin(theta), 0.6, 0.6, name="circle"
    )


def closed_loop(track: Track, model_name: str, x0: np.ndarray, seconds: float, speed: float):
    """Drive the model plant with the MPC; returns states, inputs and arc lengths per step."""
    reference = center_line(track)
    expert = MPCExpert(
        track,
        reference,
        model=model_name,
        params=PLANT_PARAMS,
        settings=MPCSettings(speed_scale=1.0),
    )
    expert.reference = _ConstantSpeed(reference, speed)
    plant = FrenetModel(model_name, PLANT_PARAMS)
    x, s, dt = x0.astype(float), 0.0, expert.settings.dt_s
    substeps, steer_angle = 5, 0.0
    lag = 1.0 - math.exp(-dt / substeps / PLANT_PARAMS.steer_time_constant_s)
    states, inputs = [], []
    for step in range(round(seconds / dt)):
        values = dict(zip(plant.state_names, x, strict=True))
        info = {
            "e_y_m": values["e_y"],
            "e_psi_rad": values["e_psi"],
            "v_x_mps": values.get("v_x", values.get("v")),
            "v_y_mps": values.get("v_y", 0.0),
            "yaw_rate_radps": values.get("r", 0.0),
            "s_m": s,
            "steer_rad": inputs[-1][0] if inputs else 0.0,
            "steer_angle_rad": steer_angle,
            "time_s": step * dt,
        }
        u = expert.act({}, info).astype(float)
        kappa = track.centerline.curvature_scalar(s)
        s += plant.s_dot(x, kappa) * dt
        for _ in range(substeps):  # the servo's first-order lag in front of the plant
            steer_angle += lag * (u[0] - steer_angle)
            x = plant.step(x, np.array([steer_angle, u[1]]), kappa, dt / substeps)
        states.append(x)
        inputs.append(u)
    return np.array(states), np.array(inputs), expert


class _ConstantSpeed:
    """A reference line with its speed profile replaced by a constant (isolates steering)."""

    def __init__(self, line, speed: float) -> None:
        self._line, self._speed = line, speed

    def offset_at(self, s):
        return self._line.offset_at(s)

    def heading_offset_at(self, s):
        return self._line.heading_offset_at(s)

    def speed_at(self, s):
        return np.full_like(np.asarray(s, dtype=float), self._speed)


@pytest.mark.parametrize("model_name", ["kinematic", "dynamic"])
def test_tracks_a_straight_line_from_an_offset(model_name: str):
    n = 4 if model_name == "kinematic" else 5
    x0 = np.zeros(n)
    x0[0], x0[2] = 0.3, 3.0  # 0.3 m left of the line at 3 m/s
    states, inputs, expert = closed_loop(stadium(), model_name, x0, seconds=3.0, speed=3.0)
    assert abs(states[-1, 0]) < 0.01 and abs(states[-1, 1]) < 0.01
    assert abs(states[-1, 2] - 3.0) < 0.05
    assert np.all(np.abs(inputs[:, 0]) <= 0.36 + 1e-6)
    assert np.all(np.abs(np.diff(inputs[:, 0])) <= 6.0 * 0.05 + 1e-6)  # steering-rate limit
    assert expert.stats.failures == 0


@pytest.mark.parametrize("model_name", ["kinematic", "dynamic"])
def test_tracks_a_circle_with_the_steady_state_steering(model_name: str):
    n = 4 if model_name == "kinematic" else 5
    x0 = np.zeros(n)
    x0[0], x0[2] = -0.2, 2.0
    states, inputs, _ = closed_loop(circle(4.0), model_name, x0, seconds=5.0, speed=2.0)
    assert np.max(np.abs(states[-20:, 0])) < 0.01
    steady_steer = np.mean(inputs[-20:, 0])
    if model_name == "kinematic":
        assert steady_steer == pytest.approx(math.atan(PLANT_PARAMS.wheelbase_m / 4.0), rel=0.01)
    else:
        assert steady_steer == pytest.approx(math.atan(PLANT_PARAMS.wheelbase_m / 4.0), rel=0.15)


def test_holds_a_straight_at_top_speed_after_a_steering_kick():
    """At 7 m/s the servo's lag is a control step: a plan that ignored it weaved on straights
    (heading swinging +-0.1 rad for good, on real circuits then a spin). After a kick the car
    must settle."""
    env = gym.make(
        "saferace/CenterLine-v0",
        track=stadium(straight_m=120.0, radius_m=20.0),
        image_size=(16, 16),
    )
    expert = MPCExpert.for_env(env)
    _, info = env.reset(seed=0, options={"start_s_m": 5.0, "start_speed_mps": 7.0})
    heading = []
    for step in range(120):
        action = expert.act({}, info)
        if step < 2:
            action[0] = 0.05
        _, _, terminated, _, info = env.step(action)
        assert not terminated
        heading.append(info["e_psi_rad"])
    env.close()
    assert info["v_x_mps"] > 6.5 and info["s_m"] < 115.0  # still on the straight, at speed
    assert max(abs(value) for value in heading[:20]) > 0.03  # the kick was felt
    assert max(abs(value) for value in heading[-40:]) < 0.01
