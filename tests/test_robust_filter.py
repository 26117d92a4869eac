"""The filter's robust mode: barrier conditions over the whole state interval, a monitor
that stops it trusting the source, and the fallback that slows to a speed the interval
fits at."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.eval.agents import make_agent
from saferace.eval.filter_config import FilterConfig
from saferace.eval.runner import make_task_env, run_episode
from saferace.names import ROBUST_GAINS
from saferace.safety.cbf.filter import SafetyFilter
from saferace.safety.cbf.filter_map import MAP_DS_M
from saferace.safety.models import MIN_SPEED_MPS
from saferace.safety.uncertainty.fallback import (
    DISTRUST_BRAKE_MPS2,
    FALLBACK_LATERAL_MPS2,
    MIN_HEADING_RAD,
    fallback_accel_bounds,
    fitting_speed_mps,
    grip_steer_rad,
    interval_margin_m,
    towards_speed,
)
from saferace.safety.uncertainty.intervals import interval_points


class IntervalSource:
    """Samples at ``mean`` with the interval ``mean +- half`` and, optionally, an alarm."""

    def __init__(self, mean: list[float], half: list[float], alarm: bool = False) -> None:
        self.mean, self.half, self.alarm = np.array(mean), np.array(half), alarm

    def reset(self, seed: int | None = None) -> None:
        """Nothing to reset."""

    def samples(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        return self.mean[None, :]

    def interval(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.mean - self.half, self.mean + self.half

    def monitor(self, samples: np.ndarray) -> tuple[float | None, bool]:
        return (10.0 if self.alarm else 1.0), self.alarm


def filtered_on_lab(source: IntervalSource, uncertainty: str, action, speed: float = 2.0):
    env = SafetyFilter(
        gym.make("saferace/CenterLine-v0", track="lab", max_laps=1),
        state_source=source,
        uncertainty=uncertainty,
        speed_limit_factor=None,
    )
    observation, info = env.reset(seed=0, options={"start_s_m": 0.5, "start_speed_mps": speed})
    env.last_trusted.reset()  # no set carried from the start: the interval alone
    decision = env.certify(observation, info, np.asarray(action, float))
    return env, decision


def test_a_control_that_breaks_the_barrier_at_one_corner_is_corrected():
    # Believed on the centre line, but the interval reaches 0.12 m to the left of it; a
    # left turn is safe for the mean and not for the interval's left corner.
    source = IntervalSource([0.0, 0.0, 0.0], [0.12, 0.01, 0.0])
    action = [0.09, 0.0]
    _, chance = filtered_on_lab(source, "chance", action)
    env, robust = filtered_on_lab(source, "robust", action)
    assert chance.filtered_action == pytest.approx(action)  # the mean alone: nothing to fix
    assert robust.intervened and robust.filtered_action[0] < action[0] - 0.04
    assert robust.fallback == ""
    # Every constraint row, one per barrier and interval point, holds at the filtered action
    # (up to what the slack penalty leaves).
    problem = env.last_problem
    points = interval_points(*source.interval(source.mean[None]))
    assert problem is not None and len(problem.b) == 4 * len(points)
    assert np.min(problem.b - problem.a @ np.array(robust.filtered_action)) > -1e-3
    assert robust.constraints["lane_left"] == pytest.approx(
        np.min((problem.b - problem.a @ np.array(robust.filtered_action))[0::4]), abs=1e-9
    )
    assert robust.state_lower[0] == pytest.approx(-0.12) and robust.state_upper[0] == 0.12


def test_the_fallback_brakes_when_the_interval_is_wider_than_the_lane():
    # lab's half widths are 0.4 m and the car's 0.15 m (+0.05 margin): +-0.25 m cannot fit.
    source = IntervalSource([0.1, 0.05, 0.0], [0.25, 0.05, 0.0])
    env, decision = filtered_on_lab(source, "robust", [0.3, 1.0])
    assert decision.fallback == "infeasible"
    assert decision.filtered_action[1] == pytest.approx(-DISTRUST_BRAKE_MPS2)
    # its own steering, not the agent's: the lane's curvature, back towards the centre
    curvature = env.track.centerline.curvature_scalar(0.5)
    steer = math.atan(env.wheelbase_m * curvature) - 0.1 - 0.05  # 1 rad per m and per rad
    assert decision.filtered_action[0] == pytest.approx(steer, abs=1e-3)
    # The same interval in the chance mode is only its samples' mean: no fallback, no brake.
    _, chance = filtered_on_lab(source, "chance", [-0.1, 1.0])
    assert chance.fallback == "" and chance.filtered_action[1] == pytest.approx(1.0)


def test_the_fallback_keeps_the_maps_speed_limit():
    # Infeasible at 6 m/s on lab, yet the interval fits the lane at that speed: without the
    # speed limit the fallback lets the agent accelerate; with it, it brakes as its row says.
    source = IntervalSource([0.0, 0.0, 0.0], [0.1, 0.1, 0.0])
    decisions, bounds = {}, {}
    for factor in (None, 1.1):
        env = SafetyFilter(
            gym.make("saferace/CenterLine-v0", track="lab", max_laps=1),
            state_source=source,
            uncertainty="robust",
            speed_limit_factor=factor,
        )
        observation, info = env.reset(seed=0, options={"start_s_m": 0.5, "start_speed_mps": 6.0})
        env.last_trusted.reset()  # the interval alone
        decisions[factor] = env.certify(observation, info, np.array([0.0, 2.0]))
        assert env.last_problem is not None
        bounds[factor] = env.last_problem.b[-1]  # the speed row's, with a limit
    assert decisions[None].fallback == decisions[1.1].fallback == "infeasible"
    assert decisions[None].filtered_action[1] == pytest.approx(2.0)
    assert bounds[1.1] < 0.0 and decisions[1.1].filtered_action[1] == pytest.approx(bounds[1.1])


def test_the_speed_row_is_the_limit_s_barrier_with_its_fall_ahead():
    """Braking into lab's first turn, the row ``accel <= lam_1 (v_limit - v) + dv_limit/ds
    v`` at the candidate offset whose limit is lowest, worked from the map's limit."""
    env = SafetyFilter(gym.make("saferace/CenterLine-v0", track="lab"), speed_limit_factor=1.1)
    filter_map, limit = env.map, env.map.speed_limit
    assert limit is not None
    grid = np.linspace(0.0, env.track.length_m, 300, endpoint=False)
    falls = np.array([limit(s + 0.05, 0.0) - limit(s, 0.0) for s in grid])
    s_m, v_x = float(grid[np.argmin(falls)]), 5.0  # where the limit falls fastest
    offsets = np.array([-0.2, 0.0, 0.25])
    values = [limit(s_m, e) for e in offsets]
    lowest = float(offsets[int(np.argmin(values))])
    slope = (limit(s_m + MAP_DS_M, lowest) - min(values)) / MAP_DS_M
    assert slope < -0.5  # falling
    row, bound, h = filter_map.speed_constraint(s_m, v_x, offsets)
    env.close()
    np.testing.assert_array_equal(row, [0.0, 1.0])
    assert h == pytest.approx(min(values) - v_x, abs=1e-12)
    assert bound == pytest.approx(filter_map.speed_gain * h + slope * v_x, abs=1e-9)


@pytest.mark.parametrize("start_s_m", [0.5, 9.0])  # a straight, a turn
def test_an_alarm_from_the_start_drives_on_the_set_carried_from_the_start_pose(
    start_s_m: float,
):
    """No frame is ever trusted; the set carried from the start pose (on the line, heading
    along it) holds the car, and the agent's hard left turn is cut to what it certifies.
    The map's speed limit stays on: the set, carried exactly, does not grow fast enough to
    stop a car the lane barriers cannot brake, and without it the car, accelerated to
    5 m/s, slid out of lab's first bend."""
    narrow = IntervalSource([0.0, 0.0, 0.0], [0.02, 0.02, 0.0], alarm=True)
    env = SafetyFilter(
        gym.make("saferace/CenterLine-v0", track="lab", max_laps=1),
        state_source=narrow,
        uncertainty="robust",
    )
    env.reset(seed=0, options={"start_s_m": start_s_m, "start_speed_mps": 2.0})
    decisions = []
    for _ in range(60):  # the agent steers hard left and accelerates all along
        info = env.step(np.array([0.3, 2.0]))[-1]
        decisions.append(info["safety"])
        assert not info["outside_lane"]
    assert all(decision["alarm"] and decision["covered"] for decision in decisions)
    assert decisions[0]["mode"] == "propagated"
    assert decisions[0]["state_upper"][0] - decisions[0]["state_lower"][0] < 0.06
    assert decisions[0]["filtered_action"][0] < 0.3  # the turn cut
    trusted = IntervalSource([0.0, 0.0, 0.0], [0.02, 0.02, 0.0])
    _, calm = filtered_on_lab(trusted, "robust", [0.0, 2.0], speed=3.0)
    assert not calm.alarm and calm.filtered_action[1] == pytest.approx(2.0)


def test_the_fitting_speed_falls_with_the_margin_and_is_a_stop_without_one():
    def speed(half_e_y: float, half_e_psi: float = 0.1) -> float:
        lower, upper = np.array([-half_e_y, -half_e_psi]), np.array([half_e_y, half_e_psi])
        return fitting_speed_mps(lower, upper, 0.5, 0.5, 0.1, creep_speed_mps=0.5)

    assert speed(0.05) > speed(0.2) > speed(0.35) >= 0.5
    assert speed(0.45) == 0.0
    assert speed(0.2, half_e_psi=0.4) < speed(0.2)
    assert fallback_accel_bounds(3.0, 0.0, 0.05) == (-DISTRUST_BRAKE_MPS2, -DISTRUST_BRAKE_MPS2)
    low, high = fallback_accel_bounds(0.2, 0.5, 0.05)
    assert low < 0.0 < high == pytest.approx(6.0)


def test_the_fitting_speed_and_the_braking_towards_it_in_numbers_worked_by_hand():
    # Offsets -0.1..0.05 in a lane 0.4 m to either side, a car 0.15 m half wide: 0.30 m to
    # the right edge at worst, 0.15 m left after the car's half width.
    lower, upper = np.array([-0.1, -0.02]), np.array([0.05, 0.1])
    assert interval_margin_m(lower, upper, 0.4, 0.4, 0.15) == pytest.approx(0.15)
    assert interval_margin_m(lower, upper, 0.4, 0.3, 0.15) == pytest.approx(0.05)
    lateral = FALLBACK_LATERAL_MPS2
    by_hand = math.sqrt(2 * lateral * 0.15) / math.sin(0.1)  # the worst heading, 0.1 rad
    assert fitting_speed_mps(lower, upper, 0.4, 0.4, 0.15, 0.3) == pytest.approx(by_hand)
    sideways = np.array([0.05, 2.0])  # past pi/2 the sine is taken at pi/2
    assert fitting_speed_mps(lower, sideways, 0.4, 0.4, 0.15, 0.3) == pytest.approx(
        math.sqrt(2 * lateral * 0.15)
    )
    square = np.array([0.05, 0.0])  # square to the lane: the least heading still counts
    assert fitting_speed_mps(-square, square, 0.4, 0.4, 0.15, 0.3) == pytest.approx(
        math.sqrt(2 * lateral * 0.2) / math.sin(MIN_HEADING_RAD)
    )
    at_the_edge = np.array([0.25, 0.0])  # no margin left, none missing: creep on
    assert fitting_speed_mps(-at_the_edge, at_the_edge, 0.5, 0.5, 0.25, 0.3) == 0.3
    dt = 0.05
    assert fallback_accel_bounds(1.0, 1.0, dt) == (-DISTRUST_BRAKE_MPS2, 0.0)  # at the target
    assert fallback_accel_bounds(0.1, 0.0, dt) == (pytest.approx(-2.0), pytest.approx(-2.0))


def test_the_oracle_makes_the_robust_filter_the_deterministic_one():
    env = SafetyFilter(
        gym.make("saferace/CenterLine-v0", track="lab", max_laps=1), uncertainty="robust"
    )
    observation, info = env.reset(seed=0, options={"start_s_m": 0.5})
    decision = env.certify(observation, info, np.array([0.3, 1.0]))
    plain = SafetyFilter(gym.make("saferace/CenterLine-v0", track="lab", max_laps=1))
    observation, info = plain.reset(seed=0, options={"start_s_m": 0.5})
    assert decision.filtered_action == pytest.approx(
        plain.certify(observation, info, np.array([0.3, 1.0])).filtered_action
    )
    assert decision.covered and decision.state_lower == decision.state_upper
    with pytest.raises(ValueError, match="uncertainty"):
        SafetyFilter(gym.make("saferace/CenterLine-v0", track="lab"), uncertainty="hopeful")


def test_a_wide_heading_interval_does_not_slow_the_robust_filter(unseen_track_csv):
    # A heading interval of +-0.16 rad: certified over it, the grip gains' first class-K
    # function (2.5 h) capped the speed at 2.5 h / sin(0.16) and braked the drift agent 20%
    # below the true state's lap. The filter holds the car over the interval's meet with
    # the set carried by odometry, whose heading is the gyro's: neither gains lose 10%.
    laps = {}
    for gains in ("grip", ROBUST_GAINS):
        for noise in (None, (0.06, 0.08)):
            config = FilterConfig(
                kind="cbf", uncertainty="robust", gains=gains, state_noise=noise, samples=20
            )
            env = make_task_env("CenterLine", str(unseen_track_csv), 1, config, 0)
            result = run_episode(env, make_agent("drift", env, seed=0), seed=0)
            env.close()
            assert result.laps[0].completed and not np.any(result.steps["lane_barrier_m"] < 0)
            laps[gains, noise is not None] = result.laps[0].lap_time_s
    assert laps[ROBUST_GAINS, True] < 1.10 * laps[ROBUST_GAINS, False]
    assert laps["grip", True] < 1.10 * laps["grip", False]


def test_a_fallback_box_moves_the_speed_to_its_target_under_the_limit_within_the_grip():
    box = (np.array([-0.1, -4.0]), np.array([0.1, 4.0]))  # a steering box tighter than grip
    lower, upper = towards_speed(box, 0.9, 1.0, 0.05, None, 0.3)
    np.testing.assert_allclose(lower, [-0.1, -DISTRUST_BRAKE_MPS2])  # its own steering kept
    np.testing.assert_allclose(upper, [0.1, (1.0 - 0.9) / 0.05])  # the target in one step
    lower, upper = towards_speed(box, 0.9, 1.0, 0.05, 1.5, 0.05)  # the map's limit, the grip
    np.testing.assert_allclose([lower[0], upper[0], upper[1]], [-0.05, 0.05, 1.5])
    lower, upper = towards_speed(box, 3.0, 1.0, 0.05, None, 0.3)  # above it: brake
    assert lower[1] == upper[1] == -DISTRUST_BRAKE_MPS2
    assert np.all(box[0] == [-0.1, -4.0])  # the box given is left as it was
    assert grip_steer_rad(2.0, 4.0, 0.25) == pytest.approx(math.atan(4.0 * 0.25 / 4.0))
    assert grip_steer_rad(0.0, 4.0, 0.25) == grip_steer_rad(MIN_SPEED_MPS, 4.0, 0.25)


def test_an_infinite_interval_is_in_doubt_whatever_the_monitor_says():
    """An interval without bounds (a calibration of too few frames, an adaptive level at
    0) rules out no state: the frame is in doubt though its monitor is calm, and the car
    drives on the set carried from the start, not on an infinite "trusted" box."""
    unbounded = IntervalSource([0.0, 0.0, 0.0], [math.inf, 0.01, 0.0])
    env = SafetyFilter(
        gym.make("saferace/CenterLine-v0", track="lab", max_laps=1),
        state_source=unbounded,
        uncertainty="robust",
    )
    env.reset(seed=0, options={"start_s_m": 0.5, "start_speed_mps": 2.0})
    decisions = [env.step(np.array([0.0, 1.0]))[-1]["safety"] for _ in range(5)]
    env.close()
    assert all(decision["alarm"] and decision["mode"] == "propagated" for decision in decisions)
    lower, upper = np.array(decisions[-1]["state_lower"]), np.array(decisions[-1]["state_upper"])
    assert np.all(np.isfinite(lower)) and upper[0] - lower[0] < 0.05  # the carried set
