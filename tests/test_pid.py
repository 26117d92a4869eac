"""The PID speed loop that turns a learned target speed into an acceleration command."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from saferace.agents.mpc import MPCExpert
from saferace.agents.pid import PIDGains, PIDSpeedController
from saferace.envs.racing_env import DEFAULT_CONTROL_HZ
from saferace.eval.runner import run_episode

DT = 1.0 / DEFAULT_CONTROL_HZ  # the tasks' control step


def simulate(controller: PIDSpeedController, target: float, drag_per_s: float, seconds: float):
    """A point mass with linear drag, driven by the controller's command."""
    speed, speeds = 0.0, []
    for _ in range(round(seconds / DT)):
        speed += (controller.command(target, speed) - drag_per_s * speed) * DT
        speeds.append(speed)
    return speeds


def test_reaches_the_target_against_drag():
    speeds = simulate(PIDSpeedController(DT), target=3.0, drag_per_s=0.3, seconds=15.0)
    assert speeds[-1] == pytest.approx(3.0, abs=0.01)  # the integral removes the drag's offset
    proportional_only = simulate(
        PIDSpeedController(DT, PIDGains(ki_per_s2=0.0)), target=3.0, drag_per_s=0.3, seconds=15.0
    )
    assert proportional_only[-1] < 2.85  # without it the drag leaves a steady error


def test_command_saturates_and_does_not_wind_up():
    controller = PIDSpeedController(DT)
    for _ in range(100):  # far below a target it cannot reach quickly: saturated all along
        assert controller.command(10.0, 0.0) == 4.0
    # At the target the command is back near zero at once: no integral piled up meanwhile.
    assert abs(controller.command(10.0, 10.0)) < 0.1


def test_reset_forgets_the_integral():
    controller = PIDSpeedController(DT)
    for _ in range(20):
        controller.command(1.0, 0.9)
    assert controller.command(1.0, 1.0) > 0.0
    controller.reset()
    assert controller.command(1.0, 1.0) == 0.0


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="gains"):
        PIDGains(kp_per_s=-1.0)
    with pytest.raises(ValueError, match="min_accel"):
        PIDGains(min_accel_mps2=1.0, max_accel_mps2=0.0)
    with pytest.raises(ValueError, match="dt_s"):
        PIDSpeedController(0.0)


class ExpertSteeringWithSpeedLoop:
    """The expert's steering, and its target-speed label through the PID: what a perfect
    control network would drive."""

    def __init__(self, env) -> None:
        self.expert = MPCExpert.for_env(env)
        self.speed_loop = PIDSpeedController(env.unwrapped.control_dt_s)

    def reset(self) -> None:
        self.expert.reset()
        self.speed_loop.reset()

    def act(self, observation, info):
        steer = self.expert.act(observation, info)[0]
        target = self.expert.planned_speed_mps()
        return np.array([steer, self.speed_loop.command(target, observation["velocity"][0])])


def test_the_target_speed_label_through_the_loop_drives_like_the_expert():
    env = gym.make("saferace/RacingLine-v0", track="lab", max_laps=1)
    try:
        expert = run_episode(env, MPCExpert.for_env(env), seed=0).summary
        imitated = run_episode(env, ExpertSteeringWithSpeedLoop(env), seed=0).summary
    finally:
        env.close()
    assert imitated["laps_completed"] == 1 and imitated["time_outside_lane_s"] == 0.0
    assert imitated["mean_lap_time_s"] == pytest.approx(expert["mean_lap_time_s"], rel=0.03)
