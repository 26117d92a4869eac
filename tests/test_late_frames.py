"""Frames that arrive late: an interval of where the car was, carried to where it is by the
odometry of the steps since, holds the car for every latency up to the declared bound (and
the bare late interval does not); the bound is the task's declaration, for a source that
reads the frame."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.eval.agents import act, make_agent
from saferace.faults.wrapper import SensorFaults
from saferace.safety.decision import nominal_parts
from saferace.safety.uncertainty.last_trusted import LastTrusted
from saferace.safety.uncertainty.late_frames import LateFrames
from saferace.safety.uncertainty.state_sources import OracleStateSource, true_lane_state
from tests.test_dead_reckoning import DoubtingSource
from tests.test_pending_commands import estimate

#: A late interval's half width ``[e_y (m), e_psi (rad)]``: what is carried is the box.
HALF_WIDTH = np.array([0.002, 0.002, 0.0])
#: What carrying adds over a few steps at most: the odometry's declared error is none, the
#: map's error per metre (``dead_reckoning.ERROR_PER_M``) a millimetre.
TOLERANCE = 1e-3


def caught_up_along_drive(
    track: str,
    faults: list[str],
    latency_steps: int,
    seconds: float,
    half_width: np.ndarray = HALF_WIDTH,
    with_set: bool = False,
) -> tuple[int, int, float]:
    """Over the expert's drive on ``track`` with ``faults``, each step an interval of
    ``half_width`` about the true state ``latency_steps`` steps before (``with_set``: the
    robust filter's set carried beside, the intervals trusted): how many steps the
    caught-up interval and how many the bare one missed the true state, and the caught-up
    offset's mean width (m)."""
    env = gym.make("saferace/CenterLine-v0", track=track, image_size=(16, 16), faults=faults)
    late = LateFrames.of_task(env, DoubtingSource())
    last_trusted = LastTrusted.of_task(env) if with_set else None
    driver = make_agent("expert", env, seed=0)
    low, high = env.action_space.low, env.action_space.high  # type: ignore[attr-defined]
    observation, info = env.reset(seed=0)
    late.reset()
    if last_trusted is not None:
        last_trusted.reset(info)
    states = [true_lane_state(info)]
    missed_caught_up = missed_bare = 0
    widths = []
    while info["time_s"] < seconds:
        seen = states[max(len(states) - 1 - latency_steps, 0)]
        interval = (seen - half_width, seen + half_width)
        truth = states[-1][:2]
        caught_up = late.caught_up(estimate(*interval), info, last_trusted)
        lower, upper = caught_up.lower, caught_up.upper
        held = (lower[:2] - TOLERANCE <= truth) & (truth <= upper[:2] + TOLERANCE)
        missed_caught_up += not np.all(held)
        missed_bare += not np.all((interval[0][:2] <= truth) & (truth <= interval[1][:2]))
        widths.append(upper[0] - lower[0])
        if last_trusted is not None:
            last_trusted.update(False, (lower, upper), info)
        command = np.clip(nominal_parts(act(driver, observation, info))[0], low, high)
        observation, _, terminated, _, info = env.step(command)
        assert not terminated
        states.append(true_lane_state(info))
    env.close()
    return missed_caught_up, missed_bare, float(np.mean(widths))


@pytest.mark.parametrize(("track", "latency_steps"), [("technical", 4), ("oval", 2), ("lab", 0)])
def test_a_late_interval_carried_by_the_odometry_holds_the_car(track: str, latency_steps: int):
    caught_up, bare, _ = caught_up_along_drive(track, ["latency:steps=4"], latency_steps, 6.0)
    assert caught_up == 0
    if latency_steps:  # the car moved on: the frame's own interval holds where it was
        assert bare > 30


def test_the_sets_heading_keeps_a_wide_heading_from_spreading_the_offset():
    """A network's heading of +-0.3 rad, carried, spreads the offset by the distance driven
    times its sine; met with the set's at each step first (a few mrad), it does not."""
    wide = np.array([0.002, 0.3, 0.0])
    faults = ["latency:steps=4"]
    alone = caught_up_along_drive("technical", faults, 4, 6.0, wide)
    with_set = caught_up_along_drive("technical", faults, 4, 6.0, wide, with_set=True)
    assert alone[0] == with_set[0] == 0
    assert with_set[2] < 0.5 * alone[2]


def test_without_a_declared_latency_nothing_is_carried():
    env = gym.make("saferace/CenterLine-v0", track="technical", image_size=(16, 16))
    _, info = env.reset(seed=0)
    box = estimate(np.zeros(3), np.ones(3))
    assert LateFrames.of_task(env, DoubtingSource()).caught_up(box, info, None) is box
    env.close()


def test_the_bound_is_the_tasks_declaration_for_a_source_that_reads_the_frame():
    env = gym.make("saferace/CenterLine-v0", track="lab", image_size=(16, 16))
    assert LateFrames.of_task(env, DoubtingSource()).max_latency_steps == 0
    faulty = SensorFaults(env, ["latency:severity=3"])
    assert LateFrames.of_task(faulty, DoubtingSource()).max_latency_steps == 4
    assert LateFrames.of_task(faulty, OracleStateSource()).max_latency_steps == 0  # never late
    with pytest.raises(ValueError, match="max_latency_steps"):
        LateFrames(-1, faulty.unwrapped.track.centerline)  # type: ignore[attr-defined]
    env.close()


def test_an_unbounded_interval_is_left_as_it_is():
    env = gym.make("saferace/CenterLine-v0", track="lab", image_size=(16, 16), faults=["latency"])
    late = LateFrames.of_task(env, DoubtingSource())
    _, info = env.reset(seed=0)
    for _ in range(3):  # steps to carry over
        _, _, _, _, info = env.step(np.array([0.0, 1.0]))
        late.caught_up(estimate(np.zeros(3), np.ones(3)), info, None)
    unbounded = dataclasses.replace(
        estimate(np.zeros(3), np.ones(3)), lower=np.full(3, -np.inf), upper=np.full(3, np.inf)
    )
    assert late.caught_up(unbounded, info, None) is unbounded
    env.close()


@pytest.mark.parametrize(
    ("faults", "widths"),
    [([], 1.0), (["blackout"], 1.0), (["latency:steps=2"], 2.0), (["delay:steps=1"], 2.0)],
)
def test_a_late_loop_is_certified_over_the_intervals_as_the_set_keeps_them(
    faults: list[str], widths: float
):
    """With frames or commands declared late, the box certified over meets the set with a
    trusted interval widened to twice its width about its centre; on time, the bare one."""
    env = gym.make("saferace/CenterLine-v0", track="lab", image_size=(16, 16), faults=faults)
    trusted = LastTrusted.of_task(env)
    assert trusted.certified_widths == widths
    _, info = env.reset(seed=0)
    trusted.reset(info)
    state = true_lane_state(info)
    half = np.array([0.004, 0.0004, 0.0])  # inside the start's set (+-0.01 m, +-0.002 rad)
    _, held = trusted.update(False, (state - half, state + half), info)
    assert held is not None
    assert held.upper - held.lower == pytest.approx(2.0 * widths * half[:2])
    with pytest.raises(ValueError, match="certified_widths"):
        LastTrusted(trusted.track, trusted.reference, certified_widths=0.5)
    env.close()
