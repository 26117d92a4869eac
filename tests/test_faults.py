"""Sensor and actuator faults: each does what it says on a recorded episode, seeded faults
repeat, the tasks take them by name, and a bad name or size is refused in one line."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import saferace  # noqa: F401  (registers the tasks)
from saferace.faults import FAULT_KINDS, FaultError, SensorFaults, parse_faults
from saferace.faults.inject import FaultInjector

DT_S = 0.05
STEPS = 60
LOW, HIGH = np.array([-0.36, -4.0], np.float32), np.array([0.36, 4.0], np.float32)


@pytest.fixture(scope="module")
def recorded() -> tuple[np.ndarray, np.ndarray]:
    """The frames and velocities of 3 s on ``lab``, steering gently left: each differs
    from the last."""
    env = gym.make("saferace/CenterLine-v0", track="lab")
    observation, _ = env.reset(seed=0)
    frames, velocities = [observation["image"]], [observation["velocity"]]
    for _ in range(STEPS):
        observation, *_ = env.step(np.array([0.05, 0.5]))
        frames.append(observation["image"])
        velocities.append(observation["velocity"])
    env.close()
    frames_array = np.array(frames)
    assert all(np.any(a != b) for a, b in zip(frames_array[1:], frames_array[:-1], strict=True))
    return frames_array, np.array(velocities)


def injected(faults: list[str], frames: np.ndarray, seed: int = 0) -> np.ndarray:
    """The frames the faulty camera gives out for ``frames``, one a control step."""
    injector = FaultInjector(parse_faults(faults), LOW, HIGH)
    injector.reset(seed)
    return np.array([injector.frame(frame, step * DT_S) for step, frame in enumerate(frames)])


def step_of(time_s: float) -> int:
    return round(time_s / DT_S)


def test_a_blackout_is_black_from_its_start_for_its_duration_and_nothing_else(recorded):
    frames, _ = recorded
    given = injected(["blackout:start=1,duration=0.5"], frames)
    during = np.arange(len(frames))
    black = (during >= step_of(1.0)) & (during < step_of(1.5))
    assert np.all(given[black] == 0) and black.sum() == 10
    np.testing.assert_array_equal(given[~black], frames[~black])


def test_a_frozen_camera_repeats_the_last_frame_before_it_froze(recorded):
    frames, _ = recorded
    given = injected(["frozen:start=1,duration=1"], frames)
    start, end = step_of(1.0), step_of(2.0)
    assert all(np.array_equal(frame, frames[start - 1]) for frame in given[start:end])
    np.testing.assert_array_equal(given[:start], frames[:start])
    np.testing.assert_array_equal(given[end:], frames[end:])


@pytest.mark.parametrize("steps", [1, 3])
def test_late_frames_are_the_frames_of_k_steps_before(recorded, steps: int):
    frames, _ = recorded
    given = injected([f"latency:steps={steps}"], frames)
    np.testing.assert_array_equal(given[steps:], frames[:-steps])
    assert all(np.array_equal(frame, frames[0]) for frame in given[:steps])  # none older


def test_a_random_latency_gives_frames_up_to_k_steps_old_and_each_age(recorded):
    frames, _ = recorded
    given = injected(["latency:steps=2,random=1"], frames)
    ages = [
        next(age for age in range(3) if np.array_equal(frame, frames[max(step - age, 0)]))
        for step, frame in enumerate(given)
    ]
    assert set(ages[2:]) == {0, 1, 2}


def test_a_dropped_frame_repeats_the_last_one_given_at_the_rate_asked(recorded):
    """Over 20 seeded episodes of 60 frames, 40% dropped: each frame is the true one or
    the last given out, and the rate of repeats lies within 4 standard deviations."""
    frames, _ = recorded
    repeats = 0
    for seed in range(20):
        given = injected(["dropped:probability=0.4"], frames, seed)
        np.testing.assert_array_equal(given[0], frames[0])
        for step in range(1, len(frames)):
            repeated = np.array_equal(given[step], given[step - 1])
            assert repeated or np.array_equal(given[step], frames[step])
            repeats += repeated
    trials = 20 * (len(frames) - 1)
    assert abs(repeats / trials - 0.4) < 4 * math.sqrt(0.4 * 0.6 / trials)


def test_an_occlusion_blacks_a_square_of_the_fraction_asked_in_one_place(recorded):
    frames, _ = recorded
    given = injected(["occlusion:fraction=0.25"], frames)
    patch = np.all(given[0] == 0, axis=-1)
    rows, columns = np.nonzero(patch)
    assert (np.ptp(rows) + 1, np.ptp(columns) + 1) == (32, 32) and patch.sum() == 32 * 32
    assert np.all(given[:, patch] == 0)  # the same place every frame
    np.testing.assert_array_equal(given[:, ~patch], frames[:, ~patch])
    corners = set()
    for seed in range(5):  # placed at random per episode
        rows, columns = np.nonzero(
            np.all(injected(["occlusion:fraction=0.25"], frames[:1], seed)[0] == 0, axis=-1)
        )
        corners.add((rows.min(), columns.min()))
    assert len(corners) > 1


def test_flicker_scales_each_frame_by_one_gain_within_its_amplitude(recorded):
    frames, _ = recorded
    given = injected(["flicker:amplitude=0.4"], frames)
    gains = []
    for frame, true in zip(given, frames, strict=True):
        unsaturated = (true > 20) & (frame < 250)
        gain = frame[unsaturated].astype(float) / true[unsaturated]
        assert gain.max() - gain.min() < 0.1  # one gain for the frame (rounding aside)
        gains.append(np.median(gain))
    assert 0.6 - 0.02 <= min(gains) < 0.9 and 1.1 < max(gains) <= 1.4 + 0.02


def test_odometry_is_biased_on_speed_and_yaw_rate_and_noisy_on_all_three(recorded):
    _, velocities = recorded
    biased = FaultInjector(parse_faults(["odometry:bias=0.05,noise=0"]), LOW, HIGH)
    out = np.array([biased.velocity(v, 1.0) for v in velocities])
    np.testing.assert_allclose(out, velocities * [1.05, 1.0, 1.05], rtol=1e-6)
    noisy = FaultInjector(parse_faults(["odometry:bias=0,noise=0.1"]), LOW, HIGH)
    noisy.reset(0)
    errors = np.array([noisy.velocity(v, 1.0) for v in velocities]) - velocities
    assert np.all(np.abs(errors.std(axis=0) - 0.1) < 0.04)


def test_a_steering_offset_and_a_delay_are_what_the_car_applies():
    """On the task: the applied command is the one given ``steps`` before (zero at first),
    off by the offset; ``info`` says so, and the wheels follow the applied one."""
    env = gym.make(
        "saferace/CenterLine-v0", track="lab", faults=["steering:offset=0.05", "delay:steps=2"]
    )
    env.reset(seed=0)
    commands = [np.array([0.1 * k - 0.1, 0.3], np.float32) for k in range(4)]
    applied, steered = [], []
    for command in commands:
        *_, info = env.step(command)
        applied.append(info["applied_action"])
        steered.append(info["steer_rad"])
    env.close()
    expected = [np.zeros(2), np.zeros(2), commands[0], commands[1]]
    np.testing.assert_allclose(applied, np.add(expected, [0.05, 0.0]), atol=1e-6)
    np.testing.assert_allclose(steered, np.array(applied)[:, 0], atol=1e-6)


def test_the_task_takes_faults_by_name_reports_them_and_repeats_them_by_seed():
    def episode(seed: int) -> tuple[list[np.ndarray], list[list[str]]]:
        env = gym.make(
            "saferace/CenterLine-v0", track="lab",
            faults=["dropped:probability=0.5", "blackout:start=0.5,duration=0.25"],
        )  # fmt: skip
        observation, info = env.reset(seed=seed)
        images, active = [observation["image"]], [info["faults"]]
        for _ in range(20):
            observation, *_, info = env.step(np.array([0.0, 0.5]))
            images.append(observation["image"])
            active.append(info["faults"])
        env.close()
        return images, active

    first, active = episode(3)
    again, _ = episode(3)
    other, _ = episode(4)
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
    assert not all(np.array_equal(a, b) for a, b in zip(first, other, strict=True))
    assert active[9] == ["dropped"] and active[10] == active[14] == ["dropped", "blackout"]
    assert active[15] == ["dropped"]


def test_the_env_checker_passes_with_every_fault():
    env = gym.make(
        "saferace/RacingLine-v0", track="lab", faults=[f"{name}:severity=3" for name in FAULT_KINDS]
    )
    check_env(env)
    check_env(SensorFaults(gym.make("saferace/RacingLine-v0", track="lab"), "latency"))
    env.close()


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("smoke", "unknown fault 'smoke'.*use blackout, frozen"),
        ("blackout:length=2", "blackout takes start, duration, severity, not 'length'"),
        ("blackout:duration=two", "duration must be a number, got 'two'"),
        ("blackout:duration", r"write blackout:KEY=VALUE"),
        ("blackout:duration=0", "duration must be above 0 s"),
        ("dropped:probability=1.5", r"probability must lie in \[0, 1\]"),
        ("latency:steps=1.5", "steps is a whole number"),
        ("frozen:severity=4", "severity is one of 1, 2, 3"),
        ("steering:start=-1", "start is seconds after the reset"),
        ("odometry:bias=0.1,bias=0.2", "bias given twice"),
    ],
)
def test_a_fault_named_or_sized_wrongly_is_refused_in_one_line(spec: str, message: str):
    with pytest.raises(FaultError, match=message):
        parse_faults([spec])


def test_a_fault_named_twice_is_refused_and_a_spec_makes_the_same_fault_again():
    with pytest.raises(FaultError, match="latency named twice"):
        parse_faults(["latency", "latency:steps=3"])
    for name in FAULT_KINDS:
        for severity in (1, 2, 3):
            fault = parse_faults([f"{name}:severity={severity},start=1.5"])[0]
            assert parse_faults([fault.spec()])[0] == fault
    blackout = parse_faults(["blackout:severity=3,start=3"])[0]
    assert (blackout.start_s, blackout.duration_s) == (3.0, 2.0)
    assert parse_faults(["dropped"])[0].duration_s == math.inf


def test_the_command_line_help_names_every_fault():
    from saferace.names import FAULTS_HELP

    assert all(name in FAULTS_HELP for name in FAULT_KINDS)
