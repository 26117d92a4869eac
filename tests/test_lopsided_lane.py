"""A lane wider on one side than the other, and narrowing on one side while it widens on the
other: every built-in track's lane is symmetric, so a left width read for a right one, or
one side's slope for the other's, passed the tests that drive on them."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.safety.cbf.filter import SafetyFilter
from saferace.safety.cbf.filter_map import FilterMap
from saferace.track.track import Track
from saferace.track.track_io import write_track_csv
from tests.track_shapes import paperclip

STRAIGHT_M, SPACING_M = 30.0, 0.2
#: On the first straight (s 0 .. 30 m): the right side 0.3 m, widening by 1 cm a metre;
#: the left 0.8 m, narrowing by 0.5 cm a metre. Elsewhere as at its end.
RIGHT_SLOPE, LEFT_SLOPE = 0.01, -0.005


def widths_at(s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The right and left half widths of :func:`lopsided` at ``s_m``, by hand."""
    along = np.clip(s_m, 0.0, STRAIGHT_M)
    return 0.3 + RIGHT_SLOPE * along, 0.8 + LEFT_SLOPE * along


@pytest.fixture(scope="module")
def lopsided(tmp_path_factory: pytest.TempPathFactory) -> str:
    x, y = paperclip(legs_apart_m=12.0, straight_m=STRAIGHT_M, spacing_m=SPACING_M)
    right, left = widths_at(np.arange(len(x)) * SPACING_M)
    path = tmp_path_factory.mktemp("tracks") / "lopsided.csv"
    write_track_csv(path, x, y, right, left)
    return str(path)


@pytest.mark.parametrize("steer_rad", [-0.1, 0.1], ids=["right", "left"])
def test_the_lane_exit_is_read_against_each_side_s_own_width(lopsided: str, steer_rad: float):
    """Steering off either side of the straight: the car is outside from the first step
    its half width (0.15 m) crosses that side's edge, and ends once all of it has."""
    env = gym.make("saferace/CenterLine-v0", track=lopsided, image_size=(16, 16))
    _, info = env.reset(seed=0, options={"start_s_m": 5.0, "start_speed_mps": 3.0})
    crossed = terminated = False
    steps = 0
    while not terminated and steps < 200:
        _, _, terminated, _, info = env.step(np.array([steer_rad, 0.0]))
        steps += 1
        right, left = widths_at(np.array(info["s_m"]))
        e_y, half = info["e_y_m"], 0.15
        assert info["w_right_m"] == pytest.approx(right, abs=2e-3)
        assert info["w_left_m"] == pytest.approx(left, abs=2e-3)
        assert info["outside_lane"] == (e_y - half < -right or e_y + half > left)
        assert info["fully_outside_lane"] == (e_y + half < -right or e_y - half > left)
        crossed = crossed or info["outside_lane"]
    env.close()
    assert crossed and terminated
    right, left = widths_at(np.array(info["s_m"]))
    if steer_rad < 0:  # all of the car past the right edge, the narrow side
        assert info["e_y_m"] + 0.15 < -right and info["e_y_m"] > -right - 0.2
    else:
        assert info["e_y_m"] - 0.15 > left and info["e_y_m"] < left + 0.3


def test_the_filter_map_reads_each_side_s_width_and_slope(lopsided: str):
    filter_map = FilterMap(Track.load(lopsided), None, 0.0, None, 1.0)  # type: ignore[arg-type]
    for s_m in (4.0, 12.5, 20.0):
        w_right, w_left, left_slope, right_slope = filter_map.widths(s_m, 0.0)
        right, left = widths_at(np.array(s_m))
        assert (w_right, w_left) == pytest.approx((right, left), abs=2e-3)
        assert left_slope == pytest.approx(LEFT_SLOPE, abs=1e-3)
        assert right_slope == pytest.approx(RIGHT_SLOPE, abs=1e-3)
    context = filter_map.barrier_context(12.5, 0.0, 0.15, 0.8, 2.5, 5.0)
    assert (context.w_right_m, context.w_left_m) == pytest.approx(
        widths_at(np.array(12.5)), abs=2e-3
    )
    assert (context.w_left_slope, context.w_right_slope) == pytest.approx(
        (LEFT_SLOPE, RIGHT_SLOPE), abs=1e-3
    )


def test_the_filter_s_lane_barriers_are_each_side_s_room(lopsided: str, tmp_path: Path):
    """At rest on the line, each lane barrier's value is its side's room: the difference
    of the two is the difference of the widths (0.5 m less the slopes' 15 cm at 10 m)."""
    env = SafetyFilter(gym.make("saferace/CenterLine-v0", track=lopsided, image_size=(16, 16)))
    env.reset(seed=0, options={"start_s_m": 10.0, "start_speed_mps": 0.0})
    _, _, _, _, info = env.step(np.array([0.0, 0.0]))
    env.close()
    barriers = info["safety"]["barriers"]
    right, left = widths_at(np.array(info["s_m"]))
    room = (left - info["e_y_m"]) - (right + info["e_y_m"])
    assert barriers["lane_left"] - barriers["lane_right"] == pytest.approx(room, abs=0.02)
