"""The recent trusted intervals and their vote: a frame that misses is outvoted, a majority
is not, a car at rest keeps no new frame, an interval wider than the set keeps none, and a
stretch of wide intervals (YasMarina's hairpins) is driven on what the frames before it
said."""

from __future__ import annotations

import itertools

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.eval.agents import act, make_agent
from saferace.names import ROBUST_GAINS
from saferace.safety.cbf.filter import GAIN_PRESETS, SafetyFilter
from saferace.safety.uncertainty.dead_reckoning import ERROR_PER_M, DeadReckoning, carried_states
from saferace.safety.uncertainty.interval_votes import (
    SPACING_M,
    VOTES,
    RecentIntervals,
    voted_box,
)
from saferace.safety.uncertainty.last_trusted import LastTrusted, cuts, offset_with_heading
from saferace.safety.uncertainty.state_sources import true_lane_state
from saferace.track.random_track import write_random_track
from tests.test_dead_reckoning import RADIUS_M, StraightLine, lane_state_on_circle, on_circle


def box(e_y: tuple[float, float], e_psi: tuple[float, float] = (0.0, 0.0)) -> tuple:
    """``(lower, upper)`` of ``[e_y, e_psi, kappa]``; carried straight ahead, a box with
    the heading known grows by the odometry's error bound alone (2 mm in 2 m)."""
    return np.array([e_y[0], e_psi[0], 0.0]), np.array([e_y[1], e_psi[1], 0.0])


def test_the_voted_box_is_the_hull_of_the_points_enough_intervals_hold():
    lower = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.5, -1.0]])
    upper = np.array([[3.0, 1.0], [4.0, 1.0], [5.0, 1.0], [2.5, 2.0]])
    three = voted_box(lower, upper, 3)
    assert three is not None
    np.testing.assert_allclose(three[0], [1.0, 0.0])  # 1 is in [0,3], [1,4], [0.5,2.5]
    np.testing.assert_allclose(three[1], [3.0, 1.0])  # 3 is in [0,3], [1,4], [2,5]
    four = voted_box(lower, upper, 4)
    assert four is not None
    np.testing.assert_allclose(four[0], [2.0, 0.0])
    np.testing.assert_allclose(four[1], [2.5, 1.0])
    apart = voted_box(np.array([[0.0], [2.0]]), np.array([[1.0], [3.0]]), 2)
    assert apart is None  # no point in both


def kept(frames: list[tuple], step_m: float = SPACING_M) -> RecentIntervals:
    """``frames`` kept one per ``step_m`` driven along a straight line."""
    recent = RecentIntervals()
    for index, frame in enumerate(frames):
        pose = np.array([index * step_m, 0.0, 0.0])
        recent.carry(pose, index * step_m, StraightLine())
        recent.add(frame, pose, index * step_m)
    return recent


def test_a_frame_that_misses_is_outvoted_and_a_majority_is_not():
    good, off = box((-0.1, 0.1)), box((0.5, 0.7))
    recent = kept([good] * (VOTES - 1) + [off])
    voted = recent.voted()
    assert voted is not None
    np.testing.assert_allclose([voted[0][0], voted[1][0]], [-0.1, 0.1], atol=3e-3)
    recent = kept([good] * 9 + [off] * 5)  # the last 9: 4 good, 5 off
    assert recent.boxes is not None and len(recent.boxes.lower) == 9
    voted = recent.voted()
    assert voted is not None
    np.testing.assert_allclose([voted[0][0], voted[1][0]], [0.5, 0.7], atol=3e-3)
    assert kept([good] * 4).voted() is None  # too few to vote
    five = kept([good] * 5).voted()  # five are enough
    assert five is not None and five[0][0] == pytest.approx(-0.1, abs=3e-3)


def test_a_car_at_rest_keeps_no_new_frame():
    at_rest = kept([box((-0.1, 0.1))] * 9, step_m=0.0)
    assert at_rest.boxes is not None and len(at_rest.boxes.lower) == 1
    creeping = kept([box((-0.1, 0.1))] * 9, step_m=0.125)  # one kept every 0.25 m: 0, .., 1 m
    assert creeping.boxes is not None and len(creeping.boxes.lower) == 5


def test_only_an_interval_that_leaves_out_part_of_the_set_votes():
    carried = DeadReckoning.trusted([-0.5, -0.01], [0.5, 0.01], [0.0, 0.0, 0.0], 0.0)
    assert cuts(carried, box((-0.3, 0.3)))
    assert cuts(carried, box((-0.9, 0.3)))  # on one side
    assert not cuts(carried, box((-0.9, 0.9), (-5.0, 5.0)))  # an unfamiliar look
    assert not cuts(carried, box((-0.9, 0.9), (-0.001, 0.001)))  # the offset decides, not
    assert cuts(carried, box((-0.3, 0.9), (-0.001, 0.001)))  # the heading
    assert cuts(None, box((-0.9, 0.9)))


def test_a_kept_interval_takes_the_set_s_heading():
    carried = DeadReckoning.trusted([-0.5, -0.01], [0.5, 0.02], [0.0, 0.0, 0.0], 0.0)
    lower, upper = offset_with_heading(box((-0.3, 0.4), (-0.4, 0.4)), carried)
    np.testing.assert_allclose(lower, [-0.3, -0.01])
    np.testing.assert_allclose(upper, [0.4, 0.02])
    lower, upper = offset_with_heading(box((-0.3, 0.4), (-0.005, 0.015)), carried)
    np.testing.assert_allclose(lower, [-0.3, -0.005])  # inside the set's: the interval's
    np.testing.assert_allclose(upper, [0.4, 0.015])


def test_in_doubt_the_votes_count_only_where_the_set_holds_their_box():
    last = LastTrusted(track=None, reference=None)  # type: ignore[arg-type]  # held only
    last.recent = kept([box((-0.1, 0.1))] * VOTES)
    inside = DeadReckoning.trusted([-0.5, -0.02], [0.5, 0.02], [0.0, 0.0, 0.0], 0.0)
    frame = box((0.05, 0.4))
    trusted = last.held(True, frame, inside)
    assert trusted is not None
    np.testing.assert_allclose([trusted.lower[0], trusted.upper[0]], [0.05, 0.1], atol=3e-3)
    assert inside.holds(inside.lower, inside.upper)  # a box on its edges is held
    in_doubt = last.held(False, frame, inside)
    assert in_doubt is not None  # the votes, not the frame
    np.testing.assert_allclose([in_doubt.lower[0], in_doubt.upper[0]], [-0.1, 0.1], atol=3e-3)
    beyond = DeadReckoning.trusted([0.0, -0.02], [0.5, 0.02], [0.0, 0.0, 0.0], 0.0)
    alone = last.held(False, frame, beyond)  # the votes reach beyond the set: not theirs
    assert alone is not None
    np.testing.assert_allclose([alone.lower[0], alone.upper[0]], [0.0, 0.5])
    outvoted = last.held(True, box((0.3, 0.4)), inside)  # the frame misses the votes' box
    assert outvoted is not None
    np.testing.assert_allclose([outvoted.lower[0], outvoted.upper[0]], [-0.1, 0.1], atol=3e-3)


class WideningSource:
    """The truth held to +-0.3 m and +-0.4 rad (a circuit's straight, as the generic model
    reads it), or, when told, to +-1.2 m and +-5 rad (a hairpin no training track has),
    its monitor quiet throughout."""

    def __init__(self) -> None:
        self.wide = False

    def reset(self, seed: int | None = None) -> None:
        """Nothing to reset."""

    def samples(self, observation: dict, info: dict) -> np.ndarray:
        return true_lane_state(info)[None]

    def interval(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        half = np.array([1.2, 5.0, 0.0]) if self.wide else np.array([0.3, 0.4, 0.0])
        return samples[0] - half, samples[0] + half

    def monitor(self, samples: np.ndarray) -> tuple[float, bool]:
        return 0.0, False


@pytest.fixture(scope="module")
def wide_lane(tmp_path_factory: pytest.TempPathFactory) -> str:
    """A 2.2 m lane (an F1TENTH circuit's) on a random track of bends (seed 8123)."""
    folder = tmp_path_factory.mktemp("tracks")
    return str(write_random_track(folder / "wide_8123.csv", 8123, 8.0, lane_width_m=2.2))


def test_a_stretch_of_wide_intervals_is_driven_on_what_the_frames_before_it_said(
    wide_lane: str,
):
    """Two seconds of +-1.2 m intervals after a drive on +-0.3 m ones long enough for the
    heading's drift to widen the carried set past +-0.5 m: the filter certifies over the
    box the earlier frames vote for, carried to the car (+-0.3 m and the distance's
    growth), which holds the truth and stays 0.2 m narrower than the carried set."""
    source = WideningSource()
    env = SafetyFilter(
        gym.make("saferace/CenterLine-v0", track=wide_lane, image_size=(16, 16)),
        state_source=source,
        uncertainty="robust",
        **GAIN_PRESETS[ROBUST_GAINS],
    )
    driver = make_agent("expert", env, seed=0)
    observation, info = env.reset(seed=0)
    for _ in range(2000):
        observation, _, _, _, info = env.step(act(driver, observation, info))
        carried = env.last_trusted.reckoning
        if carried is not None and carried.upper[0] - carried.lower[0] > 1.0:
            break
    assert carried is not None and carried.upper[0] - carried.lower[0] > 1.0
    source.wide = True
    decisions, carried_widths = [], []
    for _ in range(40):
        observation, _, _, _, info = env.step(act(driver, observation, info))
        decisions.append(info["safety"])
        carried = env.last_trusted.reckoning
        assert carried is not None
        carried_widths.append(carried.upper[0] - carried.lower[0])
    env.close()
    widths = [decision["state_upper"][0] - decision["state_lower"][0] for decision in decisions]
    assert widths[0] < 0.65 and max(widths) < 0.85  # grows with the heading's width
    assert all(held < carried - 0.2 for held, carried in zip(widths, carried_widths, strict=True))
    assert all(decision["covered"] for decision in decisions)
    assert all(decision["mode"] == "certified" for decision in decisions)


class Circle:
    """The centre line of ``tests/test_dead_reckoning.py``'s circle, as a map gives it."""

    @staticmethod
    def eval_scalar(s_m: float) -> tuple[float, ...]:
        angle = s_m / RADIUS_M
        x, y, _ = on_circle(angle)
        return x, y, np.cos(angle), np.sin(angle), 0.0, 0.0

    @staticmethod
    def pose(s_m: float) -> np.ndarray:
        return on_circle(s_m / RADIUS_M)


def test_a_stack_of_boxes_is_carried_round_a_bend_box_by_box_and_holds_the_car():
    """Three boxes with the car at a corner of each, carried by the car's move round the
    circle: each carried box is the box carried alone, and holds where polar geometry puts
    the car."""
    e_y0, e_psi0, turn = 0.3, 0.2, 0.25
    centre = on_circle(0.0)
    start = centre[:2] + e_y0 * np.array([-np.sin(centre[2]), np.cos(centre[2])])
    pose0 = np.array([*start, centre[2] + e_psi0])
    step = np.array([1.2, 0.01, turn])
    yaw = pose0[2]
    rotation = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    pose1 = np.array([*(start + rotation @ step[:2]), yaw + turn])
    e_y1, e_psi1, centre_to = lane_state_on_circle(pose1)
    s1 = float(centre_to[2]) * RADIUS_M
    lower = np.array([[e_y0, e_psi0], [e_y0 - 0.2, e_psi0], [e_y0, e_psi0 - 0.1]])
    upper = np.array([[e_y0 + 0.2, e_psi0 + 0.1], [e_y0, e_psi0 + 0.05], [e_y0 + 0.1, e_psi0]])
    stack = DeadReckoning(lower, upper, pose0, 0.0).carried(pose1, s1, Circle())
    growth = ERROR_PER_M * np.hypot(*step[:2])
    for index in range(3):
        alone = DeadReckoning(lower[index], upper[index], pose0, 0.0).carried(pose1, s1, Circle())
        np.testing.assert_allclose(stack.lower[index], alone.lower, atol=1e-12)
        np.testing.assert_allclose(stack.upper[index], alone.upper, atol=1e-12)
        corners = np.array(list(itertools.product(*zip(lower[index], upper[index], strict=True))))
        moved = np.column_stack(
            carried_states(corners[:, 0], corners[:, 1], step, centre, Circle.pose(s1))
        )  # all four corners, each carried
        np.testing.assert_allclose(stack.lower[index], moved.min(axis=0) - growth, atol=1e-12)
        np.testing.assert_allclose(stack.upper[index], moved.max(axis=0) + growth, atol=1e-12)
        assert stack.lower[index][0] <= e_y1 <= stack.upper[index][0]
        assert stack.lower[index][1] <= e_psi1 <= stack.upper[index][1]
