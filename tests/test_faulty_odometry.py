"""A faulty odometry reaches the filter: the fault wrapper integrates it into the pose the
filter carries its set by and declares how far off it may be, and the sets carried for that
hold a car whose wheels and gyro read 5% high through 2 s blackouts on bends."""

from __future__ import annotations

import itertools
import math

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.eval.agents import act, make_agent
from saferace.faults.wrapper import true_pose
from saferace.names import ODOMETRY_POSE_KEY
from saferace.safety.cbf.filter import SafetyFilter
from saferace.safety.decision import nominal_parts
from saferace.safety.uncertainty.dead_reckoning import carried_states, scale_growth
from saferace.safety.uncertainty.last_trusted import LastTrusted
from saferace.safety.uncertainty.state_sources import true_lane_state
from saferace.track.odometry import moved_by, odometry_step
from saferace.track.random_track import write_random_track

#: The blackouts: 2 s dark, then 1 s of frames, over and over.
DARK_S, LIGHT_S = 2.0, 1.0
#: The truth held to this by a frame the filter trusts ([e_y m, e_psi rad]).
TRUSTED_HALF = np.array([0.04, 0.04])


def recorded_drive(
    track: str, faults: list[str], seconds: float
) -> tuple[gym.Env, list[tuple[dict, dict]]]:
    """The expert's observation and ``info`` on ``track`` with ``faults``, every step of
    ``seconds``."""
    env = gym.make("saferace/CenterLine-v0", track=track, image_size=(16, 16), faults=faults)
    driver = make_agent("expert", env, seed=0)
    observation, info = env.reset(seed=0)
    steps = [(observation, info)]
    while info["time_s"] < seconds:
        action = nominal_parts(act(driver, observation, info))[0]
        observation, _, terminated, _, info = env.step(action)
        assert not terminated
        steps.append((observation, info))
    env.close()
    return env, steps


def test_the_odometry_pose_integrates_steps_off_as_the_velocity_reads():
    """Biased 5%, and with the noise the velocity reads integrated over the step: one
    sensor read twice."""
    _, steps = recorded_drive("lab", ["odometry:bias=0.05,noise=0.05"], 2.0)
    for (_, before), (observation, after) in itertools.pairwise(steps):
        truth = odometry_step(true_pose(before), true_pose(after))
        measured = odometry_step(before[ODOMETRY_POSE_KEY], after[ODOMETRY_POSE_KEY])
        velocity = np.array([after["v_x_mps"], after["v_y_mps"], after["yaw_rate_radps"]])
        noise_dt = (observation["velocity"] - velocity * [1.05, 1.0, 1.05]) * 0.05
        np.testing.assert_allclose(measured, truth * [1.05, 1.0, 1.05] + noise_dt, atol=2e-6)
    assert abs(steps[-1][1][ODOMETRY_POSE_KEY][2] - steps[-1][1]["yaw_rad"]) > 0.01  # drifted
    _, clean = recorded_drive("lab", ["blackout:start=0.5"], 1.0)  # a fault, not of odometry
    for _, info in clean:
        np.testing.assert_allclose(info[ODOMETRY_POSE_KEY], true_pose(info), atol=1e-9)


def test_the_filter_carries_its_sets_for_the_odometry_its_task_declares():
    faulty = gym.make("saferace/CenterLine-v0", track="lab", faults=["odometry:severity=3"])
    exact = gym.make("saferace/CenterLine-v0", track="lab", faults=["blackout"])
    try:
        assert SafetyFilter(faulty).last_trusted.odometry_scale_error == 0.1
        assert SafetyFilter(exact).last_trusted.odometry_scale_error == 0.0
    finally:
        faulty.close()
        exact.close()


def outside_in_doubt(
    trusted: LastTrusted, steps: list[tuple[dict, dict]]
) -> tuple[int, int, np.ndarray]:
    """Carry ``trusted``'s sets along ``steps`` as the robust filter does, in doubt through
    every blackout and trusting ``TRUSTED_HALF`` about the truth between: the steps in
    doubt, how many of them the truth was outside the set, and the largest miss ([e_y,
    e_psi])."""
    trusted.reset(steps[0][1])
    in_doubt = outside = 0
    worst = np.zeros(2)
    for _, info in steps[1:]:
        dark = info["time_s"] % (DARK_S + LIGHT_S) < DARK_S
        truth = true_lane_state(info)[:2]
        interval = (np.append(truth - TRUSTED_HALF, 0.0), np.append(truth + TRUSTED_HALF, 0.0))
        _, held = trusted.update(dark, interval, info)
        if dark:
            in_doubt += 1
            miss = np.maximum(held.lower - truth, truth - held.upper)
            outside += bool(np.any(miss > 0.0))
            worst = np.maximum(worst, miss)
    return in_doubt, outside, worst


@pytest.fixture(scope="module", params=[0.05, -0.05, 0.1])
def biased_drives(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> list[tuple[gym.Env, list[tuple[dict, dict]]]]:
    """40 s of the expert with odometry off by the bias on ``lab`` and on a random track of
    bends in a 2.2 m lane (seed 8123): 800 steps each, two thirds of them in the dark."""
    folder = tmp_path_factory.mktemp("tracks")
    wide = str(write_random_track(folder / "wide_8123.csv", 8123, 8.0, lane_width_m=2.2))
    faults = [f"odometry:bias={request.param},noise=0"]
    return [recorded_drive(track, faults, 40.0) for track in ("lab", wide)]


def test_blackouts_with_a_biased_odometry_keep_the_truth_in_the_set_carried_for_it(
    biased_drives: list[tuple[gym.Env, list[tuple[dict, dict]]]],
):
    counted = [outside_in_doubt(LastTrusted.of_task(env), steps) for env, steps in biased_drives]
    assert sum(in_doubt for in_doubt, _, _ in counted) >= 1000
    assert [outside for _, outside, _ in counted] == [0, 0]
    exact = [
        outside_in_doubt(LastTrusted(env.unwrapped.track, env.unwrapped.reference), steps)
        for env, steps in biased_drives
    ]  # carried for the simulator's exact odometry
    assert min(worst[0] for _, _, worst in exact) > 0.01  # lost the car by a centimetre+


def test_a_pose_moved_by_its_odometry_step_lands_where_it_was_measured_to():
    start, end = np.array([1.0, -2.0, math.pi - 0.05]), np.array([0.4, -1.7, -math.pi + 0.1])
    np.testing.assert_allclose(moved_by(start, odometry_step(start, end)), end, atol=1e-12)
    heading_north = [0.0, 0.0, math.pi / 2]  # a metre ahead, half a metre left, a quarter turn
    np.testing.assert_allclose(
        moved_by(heading_north, [1.0, 0.5, math.pi / 2]), [-0.5, 1.0, -math.pi], atol=1e-12
    )


@pytest.mark.parametrize("error", [0.05, 0.1])
def test_the_growth_holds_a_step_measured_short_by_the_error(error: float):
    """On a straight lane (centre poses along x), a car heading 0.2 rad off it drives a
    step its odometry measures ``1 - error`` times the truth: the corners carried by the
    measured and by the true step lie apart by the growth across the lane (exactly, with no
    turn), and its heading's growth covers a turn measured short."""
    e_psi = np.array([0.1, 0.2])
    measured = np.array([0.3, 0.0, 0.0])
    centre_from, centre_to = np.array([0.0, 0.0, 0.0]), np.array([0.3, 0.0, 0.0])
    e_y_measured, _ = carried_states(np.zeros(2), e_psi, measured, centre_from, centre_to)
    e_y_true, _ = carried_states(
        np.zeros(2), e_psi, measured / (1.0 - error), centre_from, centre_to
    )
    growth = scale_growth(measured, e_psi, error)
    assert np.max(np.abs(e_y_true - e_y_measured)) == pytest.approx(growth[0], rel=1e-9)
    assert growth[1] == 0.0
    turning = np.array([0.3, 0.0, 0.2])
    assert scale_growth(turning, e_psi, error)[1] == pytest.approx(0.2 * error / (1 - error))
    assert scale_growth(turning, e_psi, error)[0] > growth[0]  # the turn swings it too
