"""The stale-frame detector: a frozen or blacked-out camera is no measurement, a car
standing still in a real image stream is not a frozen camera."""

from __future__ import annotations

import itertools
import json

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.eval.agents import act, make_agent
from saferace.safety.cbf.filter import SafetyFilter
from saferace.safety.decision import nominal_parts
from saferace.safety.uncertainty.stale_frames import (
    STALE_DISTANCE_M,
    STALE_TURN_RAD,
    StaleFrames,
    stale_distance_m,
)
from saferace.safety.uncertainty.state_sources import (
    NoisyOracleStateSource,
    OracleStateSource,
    SpreadScaledStateSource,
    reads_image,
)
from saferace.track.track_io import write_track_csv
from tests.test_dead_reckoning import DoubtingSource
from tests.track_shapes import paperclip

IMAGE = np.arange(64 * 64 * 3).astype(np.uint8).reshape(64, 64, 3)


def test_a_repeat_is_stale_only_once_the_car_moved_or_turned_under_it():
    frames = StaleFrames()
    assert not frames.stale(IMAGE, np.zeros(3))
    assert not frames.stale(IMAGE.copy(), [0.9 * STALE_DISTANCE_M, 0.0, 0.0])
    assert frames.stale(IMAGE.copy(), [1.1 * STALE_DISTANCE_M, 0.0, 0.0])
    assert not frames.stale(IMAGE[::-1].copy(), [1.2 * STALE_DISTANCE_M, 0.0, 0.0])  # new
    assert frames.stale(IMAGE[::-1].copy(), [1.2 * STALE_DISTANCE_M, 0.0, 1.1 * STALE_TURN_RAD])
    frames.reset()
    assert not frames.stale(IMAGE[::-1].copy(), [5.0, 5.0, 1.0])  # nothing before it


def test_a_smaller_image_may_stay_the_same_over_a_longer_drive():
    assert stale_distance_m(64) == STALE_DISTANCE_M
    assert stale_distance_m(32) == 4 * STALE_DISTANCE_M
    small = IMAGE[::4, ::4].copy()
    frames = StaleFrames()
    assert not frames.stale(small, np.zeros(3))
    assert not frames.stale(small.copy(), [15 * STALE_DISTANCE_M, 0.0, 0.0])
    assert frames.stale(small.copy(), [17 * STALE_DISTANCE_M, 0.0, 0.0])


def test_a_frame_with_nothing_in_it_is_stale_wherever_the_car_is():
    frames = StaleFrames()
    assert frames.stale(np.zeros((4, 4, 3), np.uint8), np.zeros(3))
    assert frames.stale(np.full((4, 4, 3), 200, np.uint8), np.zeros(3))
    assert not frames.stale(IMAGE, np.zeros(3))


def drive(
    faults: list[str],
    seconds: float,
    standing: bool = False,
    track: str = "lab",
    image_size: tuple[int, int] = (64, 64),
) -> list[tuple]:
    """The expert on ``track`` (or a car held at a standstill) for ``seconds`` with
    ``faults``: each step's time, whether the detector called its frame stale, and the
    frame."""
    env = gym.make("saferace/CenterLine-v0", track=track, image_size=image_size, faults=faults)
    driver = make_agent("expert", env, seed=0)
    frames = StaleFrames()
    observation, info = env.reset(seed=0)
    steps = []
    while info["time_s"] < seconds:
        steps.append((info["time_s"], frames.in_step(observation, info), observation["image"]))
        if standing:  # braked to a standstill, never past it
            action = np.array([0.0, -min(4.0, info["v_x_mps"] / env.unwrapped.control_dt_s)])
        else:
            action = nominal_parts(act(driver, observation, info))[0]
        observation, _, terminated, _, info = env.step(action)
        assert not terminated
    env.close()
    return steps


def test_a_frozen_camera_is_caught_within_a_fifth_of_a_second_and_let_go_when_it_thaws():
    steps = drive(["frozen:start=1,duration=2"], 4.0)
    stale_times = [time_s for time_s, stale, _ in steps if stale]
    assert stale_times and 1.0 <= stale_times[0] <= 1.2
    assert max(stale_times) < 3.0 + 1e-6
    frozen = [time_s for time_s in (t for t, _, _ in steps) if 1.2 <= time_s < 3.0]
    assert set(frozen) <= set(stale_times)  # the whole time it stays frozen


def test_a_blackout_is_stale_from_its_first_frame():
    steps = drive(["blackout:start=1,duration=0.5"], 2.0)
    stale_times = [time_s for time_s, stale, _ in steps if stale]
    assert stale_times[0] == pytest.approx(1.0) and stale_times[-1] < 1.5 + 1e-6


def test_a_car_standing_still_in_a_real_image_stream_is_not_a_frozen_camera():
    steps = drive([], 3.0, standing=True)
    images = [image for time_s, _, image in steps if time_s > 1.5]
    assert all(np.array_equal(image, images[0]) for image in images)  # the same frame
    assert not any(stale for _, stale, _ in steps)


def test_a_small_image_of_a_long_straight_is_not_a_frozen_camera(tmp_path):
    """16 pixels wide, the view down a 30 m straight stays the same for metres."""
    track = tmp_path / "long_clip.csv"
    write_track_csv(track, *paperclip(legs_apart_m=12.0, straight_m=30.0), 0.45, 0.45)
    steps = drive([], 20.0, track=str(track), image_size=(16, 16))
    repeats = sum(np.array_equal(a[2], b[2]) for a, b in itertools.pairwise(steps))
    assert repeats > 10 and not any(stale for _, stale, _ in steps)


def test_the_filter_records_a_stale_frame_and_doubts_its_source_there():
    env = gym.make(
        "saferace/CenterLine-v0", track="lab", image_size=(32, 32), faults=["frozen:start=1"]
    )
    safe = SafetyFilter(env, state_source=DoubtingSource(), uncertainty="robust")
    driver = make_agent("expert", env, seed=0)
    observation, info = safe.reset(seed=0)
    records = []
    while info["time_s"] < 2.0:
        observation, _, _, _, info = safe.step(nominal_parts(act(driver, observation, info))[0])
        records.append((info["time_s"], info["safety"]))
    safe.close()
    assert not any(record["stale"] or record["alarm"] for time_s, record in records if time_s < 1)
    late = [record for time_s, record in records if time_s > 1.3]
    assert all(record["stale"] is True and record["alarm"] for record in late)
    json.dumps(late)  # as eval rows and recordings keep it
    assert {record["mode"] for record in late} <= {"propagated", "stopping"}


def test_only_a_source_that_reads_the_frame_sees_it_go_stale():
    noisy = NoisyOracleStateSource()
    assert not reads_image(OracleStateSource()) and not reads_image(noisy)
    assert not reads_image(SpreadScaledStateSource(noisy, (2.0, 2.0, 1.0)))  # wrapped truth
    assert reads_image(DoubtingSource())  # any other source: a network's
    black = {"image": np.zeros((64, 64, 3), np.uint8)}
    pose = {"x_m": 0.0, "y_m": 0.0, "yaw_rad": 0.0}
    assert not StaleFrames.of_source(noisy).in_step(black, pose)
    assert StaleFrames.of_source(DoubtingSource()).in_step(black, pose)
