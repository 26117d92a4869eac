"""The steering's centre offset, judged online from the odometry's yaw rate and undone by
the filter: found on recorded drives through the simulator's servos and tyres (either
way, under a biased odometry too), nothing found on a fault-free car, and a car stopped
blind by the fallback stops inside the lane where, uncompensated, the offset took it out."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.eval.agents import act, make_agent
from saferace.names import ROBUST_GAINS
from saferace.safety.cbf.filter import GAIN_PRESETS, SafetyFilter
from saferace.safety.decision import nominal_parts
from saferace.safety.uncertainty.steering_trim import (
    DEADBAND_RAD,
    MAX_LATERAL_ACCEL_MPS2,
    MAX_OFFSET_RAD,
    MAX_WHEELS_TURN_RAD,
    SteeringTrim,
)
from saferace.safety.vehicle_params import load_params
from tests.test_dead_reckoning import DoubtingSource

CONTROL_DT_S = 0.05
MAX_STEER_RATE_RADPS = 6.0  # the rc10's servo (saferace.envs.drivetrain)


def trim() -> SteeringTrim:
    params = load_params()
    return SteeringTrim(
        params.wheelbase_m, CONTROL_DT_S, params.steer_time_constant_s, MAX_STEER_RATE_RADPS
    )


def estimates_along_drive(track: str, faults: list[str], seconds: float = 8.0) -> np.ndarray:
    """The estimate after every step of the expert driving ``track`` with ``faults``: the
    command it sent and the velocities the (faulty) odometry measured."""
    env = gym.make("saferace/CenterLine-v0", track=track, image_size=(16, 16), faults=faults)
    driver, judge = make_agent("expert", env, seed=0), trim()
    low, high = env.action_space.low, env.action_space.high  # type: ignore[attr-defined]
    observation, info = env.reset(seed=0)
    estimates = []
    while info["time_s"] < seconds:
        command = np.clip(nominal_parts(act(driver, observation, info))[0], low, high)
        observation, _, terminated, _, info = env.step(command)
        assert not terminated
        judge.update(float(command[0]), observation["velocity"])
        estimates.append(judge.estimate_rad)
    env.close()
    return np.array(estimates)


@pytest.mark.parametrize(
    ("track", "fault", "offset_rad"),
    [
        ("technical", "steering:severity=2", 0.04),
        ("oval", "steering:offset=-0.07", -0.07),
        ("lab", "steering:offset=0.05", 0.05),
    ],
)
def test_an_offset_is_found_within_two_seconds_of_driving(
    track: str, fault: str, offset_rad: float
):
    estimates = estimates_along_drive(track, [fault])
    assert np.all(np.abs(estimates[40:] - offset_rad) < 0.006)  # from 2 s on


def test_a_biased_odometry_finds_the_same_offset():
    """Speed and yaw rate read 10% high: their ratio, the path's curvature, is not."""
    exact = estimates_along_drive("technical", ["steering:offset=0.05"])
    biased = estimates_along_drive("technical", ["steering:offset=0.05", "odometry:bias=0.1"])
    np.testing.assert_allclose(biased[40:], exact[40:], atol=0.003)


@pytest.mark.parametrize("track", ["lab", "oval", "technical", "varying"])
def test_a_fault_free_car_has_no_offset_to_undo(track: str):
    estimates = estimates_along_drive(track, [])
    assert np.abs(estimates).max() < DEADBAND_RAD / 2


def test_steps_that_say_nothing_are_skipped():
    """Slow, turning hard, or with the wheels still turning: the yaw rate is no measure of
    the wheels' angle there; a settled step at speed is."""
    judge = trim()
    judge.update(0.0, np.array([0.5, 0.0, 0.3]))  # below 1 m/s
    judge.update(0.0, np.array([5.0, 0.0, 1.2 * MAX_LATERAL_ACCEL_MPS2 / 5.0]))  # sliding
    turned = MAX_WHEELS_TURN_RAD / judge.follow * 2.0
    judge.update(turned, np.array([3.0, 0.0, 0.5]))  # the wheels turning
    assert judge.samples == 0 and judge.estimate_rad == 0.0
    for _ in range(20):  # the command held: the wheels settle; they point 0.03 rad further
        judge.update(turned, np.array([3.0, 0.0, 3.0 * np.tan(turned + 0.03) / judge.wheelbase_m]))
    assert judge.samples > 0
    assert judge.estimate_rad == pytest.approx(0.03, abs=1e-3)


def test_an_estimate_within_the_deadband_or_not_applied_is_not_undone():
    judge = trim()
    judge.servo.estimate_rad = 0.8 * DEADBAND_RAD
    assert judge.offset_rad == 0.0
    judge.servo.estimate_rad = 2.0 * DEADBAND_RAD
    assert judge.offset_rad == 2.0 * DEADBAND_RAD
    judge.applied = False
    assert judge.offset_rad == 0.0


@pytest.mark.parametrize("estimated", [True, False])
def test_a_car_stopped_blind_stops_inside_its_lane_only_with_the_offset_undone(estimated: bool):
    """The drifting driver on ``lab`` with the servo 0.07 rad off centre, its state trusted
    for 3 s, then in doubt to the end: the filter carries its set and stops the car,
    steering the lane's curvature open loop. Undone, the offset leaves it inside; not
    undone, it takes the car out of its lane and leaves it there."""
    source = DoubtingSource()
    env = SafetyFilter(
        gym.make(
            "saferace/CenterLine-v0",
            track="lab",
            image_size=(16, 16),
            faults=["steering:severity=3"],
        ),
        state_source=source,
        uncertainty="robust",
        estimate_steering_offset=estimated,
        **GAIN_PRESETS[ROBUST_GAINS],
    )
    driver = make_agent("drift", env, seed=0)
    observation, info = env.reset(seed=0)
    infos = []
    for _ in range(200):
        source.alarm = info["time_s"] >= 3.0
        action = nominal_parts(act(driver, observation, info))[0]
        observation, _, _, _, info = env.step(action)
        infos.append(info)
    env.close()
    decisions = [step["safety"] for step in infos]
    outside_steps = sum(step["outside_lane"] for step in infos)
    assert decisions[-1]["mode"] == "stopping" and abs(infos[-1]["v_x_mps"]) < 0.01
    if estimated:
        assert outside_steps == 0
        assert decisions[-1]["steering_offset_rad"] == pytest.approx(0.07, abs=0.006)
        wheels = [step["applied_action"][0] for step in infos[-100:]]  # command and offset
        wanted = [decision["filtered_action"][0] for decision in decisions[-100:]]
        np.testing.assert_allclose(wheels, wanted, atol=0.006)  # what the filter meant
    else:
        assert outside_steps > 50 and infos[-1]["outside_lane"]
        assert all(decision["steering_offset_rad"] == 0.0 for decision in decisions)


def test_an_offset_that_sets_in_is_taken_within_a_few_steps_not_the_memory():
    estimates = estimates_along_drive("technical", ["steering:start=3,offset=0.04"], seconds=3.5)
    onset = round(3.0 / CONTROL_DT_S)
    assert np.all(np.abs(estimates[:onset]) < DEADBAND_RAD)
    assert estimates[onset + 4] == pytest.approx(0.04, abs=0.006)  # 0.2 s on, not 0.03 by then


def test_an_onset_is_told_on_steps_that_slide_or_turn_the_wheels():
    """The speeding driver at 7 m/s on a 0.7 m lane, its servo 0.07 rad off from 3 s (the
    fault table's trace): the first step's yaw lags the wheels, the second slides beyond the
    grip and the filter's countersteer turns the wheels on the third. None is a clean
    measure, but neither slip nor lag turns the car further than its wheels: the estimate
    restarts on the second (it read 0.007 until two clean steps later, the car outside)."""
    judge = trim()
    for _ in range(40):
        judge.update(0.0, np.array([7.05, 0.0, 0.0]))
    judge.update(0.0, np.array([7.05, 0.09, 0.80]))
    judge.update(-0.008, np.array([7.04, 0.13, 1.17]))  # 8.2 m/s^2
    assert judge.estimate_rad == pytest.approx(0.07, abs=0.012)


def test_tyres_sliding_short_of_the_wheels_restart_nothing():
    """Beyond the grip the car turns less than its wheels: a yaw rate short of them is no
    new offset, however far short."""
    judge = trim()
    command = 0.1
    for _ in range(40):  # settled in a bend at 3 m/s, inside the grip
        judge.update(command, np.array([3.0, 0.0, 3.0 * np.tan(command) / judge.wheelbase_m]))
    settled = judge.estimate_rad
    for _ in range(20):  # at 7 m/s the yaw rate of 0.06 rad where the wheels hold 0.1
        judge.update(command, np.array([7.0, 0.0, 7.0 * np.tan(0.06) / judge.wheelbase_m]))
    assert judge.servo.surprises == 0
    assert judge.estimate_rad == settled


def test_a_spinning_car_gives_no_offset():
    """The speeding driver on Monza, behind the paper's gain and the generic model, spun:
    its yaw rate said the wheels held a radian more than they did, twice, and the estimate
    restarted at 1.06 rad, beyond the steering's range. No offset explains a spin."""
    judge = trim()
    for _ in range(40):
        judge.update(0.0, np.array([6.0, 0.0, 0.0]))
    for yaw_rate in (12.0, 14.0, 15.0):  # sliding, and turning far more than the wheels
        judge.update(0.0, np.array([6.0, 1.5, yaw_rate]))
    assert judge.estimate_rad == 0.0 and judge.servo.surprises == 0
    offset = MAX_OFFSET_RAD - 0.01  # the most an offset may be is still found
    for _ in range(60):
        judge.update(0.0, np.array([3.0, 0.0, 3.0 * np.tan(offset) / judge.wheelbase_m]))
    assert judge.estimate_rad == pytest.approx(offset, abs=1e-3)
