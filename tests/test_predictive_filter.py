"""The predictive safety filter (MPSF): it sees a turn coming, falls back on its certified
plan, moves a stopped car on, and sits behind the same wrapper and options as the CBF."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.errors import ConfigError
from saferace.eval.filters import FilterConfig, apply_filter
from saferace.experiments.filter_benchmark import FilterEntry, drive_filter_run
from saferace.experiments.filter_suite import FilterRunSpec, load_filter_suite
from saferace.safety.predictive import filter as predictive
from saferace.safety.predictive.filter import PredictiveSafetyFilter
from saferace.safety.uncertainty.state_sources import true_lane_state
from saferace.track.track_io import write_track_csv
from tests.track_shapes import paperclip

STRAIGHT_M = 12.0  # the paperclip's first straight ends, and its 1.5 m hairpin begins, here


@pytest.fixture(scope="module")
def hairpin_track(tmp_path_factory: pytest.TempPathFactory) -> str:
    """Straights 3 m apart joined by half circles of 1.5 m radius, in a 1.2 m lane."""
    path = tmp_path_factory.mktemp("tracks") / "paperclip.csv"
    write_track_csv(path, *paperclip(legs_apart_m=3.0, straight_m=STRAIGHT_M), 0.6, 0.6)
    return str(path)


def make_env(track: str = "lab", **kwargs) -> gym.Env:
    return gym.make("saferace/CenterLine-v0", track=track, max_laps=1, **kwargs)


def straight_on(env: gym.Env, start_s_m: float, speed_mps: float, steps: int) -> tuple[int, dict]:
    """Drive ``[steer 0, accel 0]`` (straight on, coasting) from ``start_s_m``: the steps
    spent outside the lane, and the last step's info."""
    _, info = env.reset(seed=0, options={"start_s_m": start_s_m, "start_speed_mps": speed_mps})
    outside = 0
    for _ in range(steps):
        _, _, terminated, truncated, info = env.step(np.zeros(2))
        outside += info["cost"] > 0.0
        if terminated or truncated:
            break
    return outside, info


def test_a_turn_within_the_horizon_bends_an_action_that_is_safe_where_the_car_is(
    hairpin_track: str,
):
    """Straight on at 4 m/s, coasting, towards a hairpin whose speed limit is 2.9 m/s:
    untouched far from it; bent while the car is still on the straight, square to a lane
    it is far inside (safe where it is), since the plan over the next second meets the
    turn; and the car goes round inside the lane, where unfiltered it leaves."""
    env = PredictiveSafetyFilter(make_env(hairpin_track))
    observation, info = env.reset(seed=0, options={"start_s_m": 1.0, "start_speed_mps": 3.0})
    far = env.certify(observation, info, np.zeros(2))
    assert not far.intervened and far.filtered_action == pytest.approx([0.0, 0.0], abs=1e-2)

    _, info = env.reset(seed=0, options={"start_s_m": STRAIGHT_M - 4.0, "start_speed_mps": 4.0})
    first_bent, outside = None, 0
    for _ in range(80):
        before = info
        _, _, terminated, truncated, info = env.step(np.zeros(2))
        outside += info["cost"] > 0.0
        if first_bent is None and info["safety"]["intervened"]:
            first_bent = before, info["safety"]
        if terminated or truncated:
            break
    assert first_bent is not None
    where, decision = first_bent
    assert where["s_m"] < STRAIGHT_M - 1.0 and abs(where["kappa_radpm"]) < 1e-2  # a straight
    assert min(decision["barriers"]["lane_left"], decision["barriers"]["lane_right"]) > 0.15
    assert decision["filtered_action"][1] < -0.05  # it brakes for what lies ahead
    assert outside == 0 and info["s_m"] > STRAIGHT_M + np.pi * 1.5  # round the hairpin

    free = make_env(hairpin_track)
    outside_free, _ = straight_on(free, STRAIGHT_M - 4.0, 4.0, 80)
    assert outside_free > 0  # straight on leaves the lane in the hairpin
    env.close()
    free.close()


def test_an_infeasible_plan_follows_the_tail_of_the_last_certified_one():
    """Where no plan keeps the lane and the speed limit (here: far too fast for the map)
    and the car is where the last certified plan expects it, that plan's next input is
    applied: the MPSC fallback."""
    env = PredictiveSafetyFilter(make_env())
    observation, info = env.reset(seed=0, options={"start_speed_mps": 2.0})
    assert len(env._tail_inputs) == len(env._tail_states) == 0  # no plan yet, no tail
    certified = env.certify(observation, info, np.array([0.0, 1.0]))
    assert not certified.fallback and certified.status == certified.mode == "certified"
    expected = env.planner.plan_states
    tail = env._tail_inputs.copy()  # the plan's later inputs, where it expects each
    np.testing.assert_allclose(tail[:, 0], env.planner.plan_inputs[1:, 0])
    np.testing.assert_allclose(env._tail_states, expected[1:-1, :2])
    too_fast = {**observation, "velocity": np.array([9.0, 0.0, 0.0], dtype=np.float32)}
    for step in (1, 2):  # the tail's inputs in turn, while the car is where it expects
        at_plan = {
            **info, "e_y_m": float(expected[step, 0]), "e_psi_rad": float(expected[step, 1])
        }  # fmt: skip
        decision = env.certify(too_fast, at_plan, np.array([0.0, 1.0]))
        assert decision.fallback == "infeasible" and decision.status == "uncertified"
        assert decision.mode == "propagated"  # the last certified plan, carried on
        assert decision.filtered_action == pytest.approx(
            np.clip(tail[step - 1], env.lower, env.upper)
        )
    assert len(env._tail_inputs) == len(env._tail_states) == len(tail) - 2
    elsewhere = {**at_plan, "e_y_m": at_plan["e_y_m"] + 0.15}  # not where the plan expects
    replanned = env.certify(too_fast, elsewhere, np.array([0.0, 1.0]))
    assert replanned.fallback == "infeasible" and replanned.mode == "stopping"
    assert replanned.filtered_action[1] < -1.0  # the least-violating plan: it brakes
    env.close()


def test_a_plans_last_stage_is_held_to_the_maps_invariant_limit(hairpin_track: str):
    """Every stage's speed cap is the map's limit where the stage is linearised (and the
    grip's), but the last stage's, the terminal set's, is the invariant limit: off the
    racing line in the hairpin, below the blended one."""
    env = PredictiveSafetyFilter(
        gym.make("saferace/RacingLine-v0", track=hairpin_track, max_laps=1)
    )
    env.reset(seed=0)
    planner, limit = env.planner, env.planner.speed_limit
    assert limit is not None
    s_m = np.linspace(STRAIGHT_M - 2.0, STRAIGHT_M + 3.0, planner.settings.horizon)
    line = planner.reference.offset_at(s_m)
    candidates = [line[-1] + d for d in np.linspace(-0.55, 0.55, 23)]
    gaps = [limit.along(s_m[-1:], np.array([e]))[0] - limit.invariant_limit(s_m[-1], e)
            for e in candidates]  # fmt: skip
    assert max(gaps) > 0.3  # an offset where the blend is well above the invariant limit
    states = np.zeros((len(s_m), planner.model.n_state + 1))
    states[:, 0] = line
    states[-1, 0] = candidates[int(np.argmax(gaps))]
    states[:, planner.model.speed_index] = 3.0
    caps = planner._speed_caps_mps(s_m, states)
    grip = np.sqrt(planner.max_lateral_accel_mps2 * planner.params.wheelbase_m / 1e-6)
    expected = np.minimum(grip, limit.along(s_m, states[:, 0]))
    expected[-1] = min(grip, limit.invariant_limit(s_m[-1], states[-1, 0]))
    np.testing.assert_allclose(caps, expected, rtol=0, atol=1e-12)
    env.close()


def test_a_stage_whose_wheels_are_turned_is_capped_at_the_tyres_grip(hairpin_track: str):
    """With the wheels at 0.3 rad, the speed at which a kinematic car's lateral
    acceleration ``v^2 tan(delta) / L`` reaches the grip is below the map's limits: that
    stage's cap; the straight-wheeled stages keep the map's."""
    env = PredictiveSafetyFilter(
        gym.make("saferace/RacingLine-v0", track=hairpin_track, max_laps=1)
    )
    env.reset(seed=0)
    planner, limit = env.planner, env.planner.speed_limit
    assert limit is not None
    s_m = np.linspace(2.0, 6.0, planner.settings.horizon)  # on the straight
    states = np.zeros((len(s_m), planner.model.n_state + 1))
    states[:, 0] = planner.reference.offset_at(s_m)
    states[:, planner.model.speed_index] = 3.0
    turned = [3, 7]
    states[turned, -1] = [0.3, -0.3]  # left and right
    caps = planner._speed_caps_mps(s_m, states)
    grip_mps = np.sqrt(planner.max_lateral_accel_mps2 * planner.params.wheelbase_m / np.tan(0.3))
    map_limits = limit.along(s_m, states[:, 0])
    assert grip_mps < map_limits[turned].min() - 0.5  # the grip binds there
    np.testing.assert_allclose(caps[turned], grip_mps, rtol=1e-12)
    straight = [k for k in range(len(s_m) - 1) if k not in turned]
    np.testing.assert_allclose(caps[straight], map_limits[straight], rtol=1e-12)
    env.close()


def test_each_stage_s_steering_is_bounded_by_the_grip_at_its_own_speed(hairpin_track: str):
    """A plan speeding up from 1 to 8 m/s: each stage's steering within the lock (where
    the grip allows more: at 1 m/s) or ``atan(a L / v^2)`` at that stage's own
    speed, whichever is less; the first stage's within the bounds asked for too."""
    env = PredictiveSafetyFilter(
        gym.make("saferace/RacingLine-v0", track=hairpin_track, max_laps=1)
    )
    env.reset(seed=0)
    planner = env.planner
    horizon = planner.settings.horizon
    plan_x = np.zeros((horizon + 1, planner.model.n_state + 1))
    speeds = np.linspace(1.0, 8.0, horizon + 1)
    plan_x[:, planner.model.speed_index] = speeds
    planner.first_bounds = (np.array([0.05, -1.0]), np.array([0.3, 1.0]))
    u_min, u_max = planner._input_bounds(plan_x)
    plan_x[1:, planner.model.speed_index] = 8.0  # the first stage slow, the rest fast
    planner.first_bounds = (np.array([-1.0, -10.0]), np.array([1.0, 10.0]))  # none binds
    first_min, first_max = (bound[0] for bound in planner._input_bounds(plan_x))
    env.close()
    params = planner.drivetrain  # the car's lock, brake and drive
    lock, accel_min, accel_max = params.max_steer_rad, -params.max_brake_mps2, params.max_accel_mps2
    grip = np.arctan(planner.max_lateral_accel_mps2 * planner.params.wheelbase_m / speeds[:-1] ** 2)
    expected_max = np.minimum(lock, grip)
    np.testing.assert_allclose(u_max[1:, 0], expected_max[1:], rtol=1e-12)
    np.testing.assert_allclose(u_min[1:, 0], -expected_max[1:], rtol=1e-12)
    assert grip[0] > lock and grip[-1] < 0.1  # both ends bind somewhere
    np.testing.assert_allclose(u_min[0], [0.05, -1.0])  # the first stage: as asked
    np.testing.assert_allclose(u_max[0], [0.3, 1.0])
    np.testing.assert_allclose(u_min[1:, 1], accel_min)
    np.testing.assert_allclose(u_max[1:, 1], accel_max)
    np.testing.assert_allclose(first_min, [-lock, accel_min])  # its own, not stage 1's grip
    np.testing.assert_allclose(first_max, [lock, accel_max])


def test_a_plan_s_first_steering_moves_from_the_last_command_by_the_rate_limit(
    hairpin_track: str,
):
    """Heading for the left edge with the wheels at 0.3 rad left: the plan turns right as
    fast as it may, the first steering 0.3 rad a stage less than the last command's."""
    env = PredictiveSafetyFilter(
        gym.make("saferace/RacingLine-v0", track=hairpin_track, max_laps=1)
    )
    env.reset(seed=0)
    planner = env.planner
    x0 = np.append(planner.model.state_from(0.2, 0.4, 4.0), 0.3)
    bounds = (np.array([-0.36, -6.0]), np.array([0.36, 6.0]))
    u, solved = planner.plan(
        x0, 2.0, 0.3, np.array([0.3, 0.0]), np.array([0.0, 0.0]), bounds, 0.0, 0.0
    )
    env.close()
    assert solved
    assert u[0] == pytest.approx(0.3 - 0.3, abs=1e-6)  # at the rate limit from 0.3 rad


def test_a_stage_beyond_the_last_plan_s_arc_lengths_holds_to_no_old_limit(hairpin_track: str):
    """The last plan held its stages' arc lengths to their limits; arc lengths before or
    after that stretch are held to none, a lap on is the same stretch, and a failed plan
    is never certified."""
    env = PredictiveSafetyFilter(
        gym.make("saferace/RacingLine-v0", track=hairpin_track, max_laps=1)
    )
    env.reset(seed=0)
    planner = env.planner
    planner._held_limits = (np.array([5.0, 6.0, 7.0]), np.array([3.0, 2.5, 2.0]))
    held = planner._held_limit(np.array([4.0, 5.5, 6.5, 8.0]))
    np.testing.assert_array_equal(held, [-np.inf, 2.75, 2.25, -np.inf])
    lap = planner.track.length_m
    np.testing.assert_array_equal(planner._held_limit(np.array([5.5, 6.5]) + lap), [2.75, 2.25])
    planner._plan_slack = None  # as a failed solve leaves it
    assert planner.plan_slacks is None and not planner.certified
    env.close()


def test_a_stages_map_limit_holds_what_the_last_steps_plan_held_it_to(hairpin_track: str):
    """A plan moved off the racing line does not meet map limits below those the last
    step's plan met at the same arc lengths (the blend falls by metres per second over
    tenths of a metre): the shifted certified plan stays feasible. The last stage is still
    held to the invariant limit where it now lies, and a lap's wrap changes nothing."""
    env = PredictiveSafetyFilter(
        gym.make("saferace/RacingLine-v0", track=hairpin_track, max_laps=1)
    )
    env.reset(seed=0, options={"start_s_m": STRAIGHT_M - 2.0, "start_speed_mps": 3.0})
    env.step(np.array([0.0, 0.0]))
    planner, limit = env.planner, env.planner.speed_limit
    assert limit is not None
    held_s_m, held = planner._held_limits
    s_m = np.append(held_s_m[2:], held_s_m[-1] + np.diff(held_s_m[-2:])) + 0.05
    states = np.zeros((len(s_m), planner.model.n_state + 1))
    states[:, 0] = planner.reference.offset_at(s_m) + 0.55  # off the line, towards the edge
    states[:, planner.model.speed_index] = 3.0
    caps = planner._speed_caps_mps(s_m, states)
    blend = limit.along(s_m, states[:, 0])
    grip = np.sqrt(planner.max_lateral_accel_mps2 * planner.params.wheelbase_m / 1e-6)
    held_there = np.interp(s_m, held_s_m, held, left=-np.inf, right=-np.inf)
    expected = np.minimum(grip, np.maximum(blend, held_there))
    expected[-1] = min(grip, limit.invariant_limit(s_m[-1], states[-1, 0]))
    np.testing.assert_allclose(caps, expected, rtol=0, atol=1e-12)
    assert np.max(caps[:-1] - blend[:-1]) > 0.3  # the held limit is well above the blend
    wrapped = planner._speed_caps_mps(s_m - planner.track.length_m, states)
    np.testing.assert_allclose(wrapped, caps, rtol=0, atol=1e-9)
    env.close()


def test_a_stopped_car_heading_for_the_edge_is_moved_on_and_steered_away():
    """At a standstill near the left edge and heading out, the plan drives on and turns
    away, certified, rather than hold the car there; a stopped car whose agent pushes for
    the edge drives on inside the lane."""
    env = PredictiveSafetyFilter(make_env())
    observation, info = env.reset(seed=0, options={"start_speed_mps": 0.0})
    observation = {**observation, "velocity": np.zeros(3, dtype=np.float32)}
    info = {**info, "e_y_m": 0.12, "e_psi_rad": 0.2, "steer_angle_rad": 0.0, "steer_rad": 0.0}
    decision = env.certify(observation, info, np.array([0.1, 2.0]))
    assert not decision.fallback and decision.filtered_action[1] > 0.5  # it drives on ...
    assert env.planner.plan_inputs[:, 0].min() < -0.2  # ... planning to turn away ...
    assert decision.constraints["lane_left"] >= -0.01  # ... inside the lane

    _, info = env.reset(seed=0, options={"start_speed_mps": 0.0})
    start_s_m = info["s_m"]
    for _ in range(40):  # 2 s of an agent pushing for the left edge at full lock
        _, _, terminated, truncated, info = env.step(np.array([0.36, 2.0]))
        assert info["cost"] == 0.0 and not (terminated or truncated)
    assert info["s_m"] - start_s_m > 2.0 and info["v_x_mps"] > 0.5  # moved on, not held
    env.close()


def test_a_car_stopped_in_a_tight_turn_heading_out_is_planned_on_never_in_reverse(
    tmp_path: Path,
):
    """Stopped in a 0.8 m hairpin (a circuit's kink: the lane turns about as tightly as
    the car can), 0.4 m from the outer edge, heading 0.5 rad out, with an uncertain state
    (0.1 m and 0.1 rad half-intervals): the plan is certified, its first input drives on,
    no stage's speed is negative, and it ends turned back towards the lane's direction.

    Linearised at a standstill, where the models raise the speed to 0.5 m/s inside, the
    plan reversed at up to 2 m/s (which turned the car in place in the model) and held
    the car: the weave agent on noisy state stood 90 s in a kink of Melbourne."""
    path = tmp_path / "tight_hairpin.csv"
    write_track_csv(path, *paperclip(legs_apart_m=1.6, straight_m=6.0), 0.6, 0.6)
    env = PredictiveSafetyFilter(make_env(str(path)))
    env.reset(seed=0)
    planner = env.planner
    mid_turn_s_m = 6.0 + np.pi * 0.4  # the hairpin turns left: its outer edge is the right
    assert env.track.centerline.curvature_scalar(mid_turn_s_m) > 1.2
    x0 = np.append(planner.model.state_from(-0.1, -0.5, 0.0), 0.36)
    box = (np.array([-0.36, 0.0]), np.array([0.36, 4.0]))  # no braking at a standstill
    weight = 1.0 / np.array(env.action_std) ** 2  # the agent's action, at the default spread
    first, _ = planner.plan(x0, mid_turn_s_m, 0.36, np.array([0.0, 2.0]), weight, box, 0.1, 0.1)
    speeds = planner.plan_states[:, planner.model.speed_index]
    assert planner.certified and first[1] > 0.5
    assert speeds.min() >= -1e-3 and speeds[-1] > 0.5
    assert abs(planner.plan_states[-1, 1]) < 0.5 - 0.02  # turning back
    env.close()


def test_the_filter_config_builds_the_predictive_filter_with_its_own_model():
    env = apply_filter(make_env(), FilterConfig(kind="mpsf", state_noise=(0.05, 0.05)), seed=0)
    assert isinstance(env, PredictiveSafetyFilter)
    assert env.planner.model.name == "dynamic"  # auto: the family's model
    assert FilterConfig(kind="cbf").model == "kinematic"
    assert FilterConfig(kind="mpsf", state_noise=(0.05, 0.05)).label == "mpsf-noisy-prob"
    with pytest.raises(ConfigError, match="slack"):
        FilterConfig(kind="mpsf", slack="l1")
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([0.0, 0.0]))
    safety = info["safety"]
    assert set(safety["constraints"]) == set(predictive.PREDICTIVE_CONSTRAINTS)
    assert safety["tightening"]["lane_left"] > 0.05  # the noisy state's interval: z * 0.05 m
    env.close()


class TruthInABox:
    """The true lane state, held to the interval ``truth - below .. truth + above``
    (``truth +- half``)."""

    def __init__(self, half: list[float], above: list[float] | None = None) -> None:
        self.below = np.array(half)
        self.above = self.below if above is None else np.array(above)

    def reset(self, seed: int | None = None) -> None:
        """Nothing to reset."""

    def samples(self, observation: dict[str, np.ndarray], info: dict) -> np.ndarray:
        return true_lane_state(info)[None]

    def interval(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return samples[0] - self.below, samples[0] + self.above


def test_an_interval_keeps_the_driven_car_its_half_width_further_from_the_edge():
    """A driver steering hard left on ``lab``'s straight rides the lane's edge behind the
    filter; known to +-0.12 m, the car rides there less those 0.12 m, not less nothing and
    not far less."""
    rides = {}
    for half_m in (0.0, 0.12):
        env = PredictiveSafetyFilter(
            make_env(), state_source=TruthInABox([half_m, 0.0, 0.0]), uncertainty="robust"
        )
        env.reset(seed=0, options={"start_speed_mps": 2.0})
        offsets = [env.step(np.array([0.35, 0.0]))[-1]["e_y_m"] for _ in range(40)]
        rides[half_m] = max(offsets[20:])  # after it reached the edge
        env.close()
    assert rides[0.0] > 0.15  # the driver does push the car to the edge
    assert rides[0.0] - 0.12 - 0.02 <= rides[0.12] <= rides[0.0] - 0.12 + 0.01, rides


def test_a_filter_on_the_mean_ignores_the_interval_and_a_robust_one_believes_its_centre():
    box = TruthInABox([0.12, 0.0, 0.0], above=[0.0, 0.0, 0.0])  # reaching 12 cm right
    deterministic = PredictiveSafetyFilter(make_env(), state_source=box, probabilistic=False)
    robust = PredictiveSafetyFilter(make_env(), state_source=box, uncertainty="robust")
    for env in (deterministic, robust):
        observation, info = env.reset(seed=0, options={"start_speed_mps": 2.0})
        decision = env.certify(observation, info, np.array([0.0, 0.0]))
        w_left = float(env.unwrapped.track.widths(info["s_m"])[1])
        believed = info["e_y_m"] - (0.06 if env is robust else 0.0)
        assert decision.barriers["lane_left"] == pytest.approx(w_left - believed - env.half_width_m)
        assert decision.tightening["lane_left"] == (0.06 if env is robust else 0.0)
        assert env.planner.heading_margin_rad == 0.0
        env.close()
    for heading_half, margin in ((0.3, 0.3), (2.0, 0.5 * np.pi)):  # at most a right angle
        env = PredictiveSafetyFilter(
            make_env(), state_source=TruthInABox([0.0, heading_half, 0.0]), uncertainty="robust"
        )
        observation, info = env.reset(seed=0, options={"start_speed_mps": 2.0})
        env.certify(observation, info, np.array([0.0, 0.0]))
        assert env.planner.heading_margin_rad == pytest.approx(margin)
        env.close()


def test_noisy_state_tightens_the_lane_and_the_drift_agent_stays_inside(tmp_path: Path):
    """The drift agent on ``oval`` behind the predictive filter fed noisy state samples."""
    from saferace.eval.runner import evaluate

    (row,) = evaluate(
        "drift",
        "CenterLine",
        "oval",
        [0],
        progress=False,
        safety=FilterConfig(kind="mpsf", state_noise=(0.05, 0.05)),
        env_kwargs={"max_steps": 300},
    )
    free = evaluate("drift", "CenterLine", "oval", [0], progress=False)[0]
    assert free["summary"]["time_outside_lane_s"] > 0.0
    assert row["summary"]["time_outside_lane_s"] == 0.0
    assert row["filter_solver"]["solve_median_ms"] > 0.0


def test_a_decision_reports_its_margins_now_and_over_the_plan_and_the_filter_counts_them():
    """Fed the truth on ``lab``: a gentle nominal passes unchanged, a hard left turn is
    corrected; every decision's margins are the lane's and the heading bound's at the car
    (from the env's own state) and the least over its plan, and the counts add up."""
    env = PredictiveSafetyFilter(make_env())
    _, after = env.reset(seed=0, options={"start_speed_mps": 0.5})
    track, planner, half = env.unwrapped.track, env.planner, env.half_width_m
    limit = env.map.speed_limit
    assert limit is not None
    decisions = []
    for nominal in [[0.02, 0.3]] * 4 + [[0.45, 2.0]] * 12:
        before, after = after, env.step(np.array(nominal))[-1]  # decided on the state before
        decision = after["safety"]
        decisions.append(decision)
        w_right, w_left = (float(w) for w in track.widths(before["s_m"]))
        e_y, e_psi, v_x = before["e_y_m"], before["e_psi_rad"], before["v_x_mps"]
        assert decision["barriers"]["lane_left"] == pytest.approx(w_left - e_y - half)
        assert decision["barriers"]["lane_right"] == pytest.approx(w_right + e_y - half)
        bound = planner.terminal_heading_rad + planner.terminal_heading_per_mps * v_x
        assert decision["barriers"]["terminal_heading"] == pytest.approx(bound - abs(e_psi))
        speed_margin = limit(before["s_m"], e_y) - v_x
        assert decision["barriers"]["speed"] == pytest.approx(speed_margin)
        assert set(decision["tightening"].values()) == {0.0}  # the truth: nothing to tighten
    states, s_plan = planner.plan_states, planner.plan_arc_lengths
    w_right, w_left = track.widths(s_plan)
    over_plan = decisions[-1]["constraints"]
    assert over_plan["lane_left"] == pytest.approx(np.min(w_left - states[:, 0]) - half)
    assert over_plan["lane_right"] == pytest.approx(np.min(w_right + states[:, 0]) - half)
    speeds = states[:, planner.model.speed_index]
    assert over_plan["speed"] == pytest.approx(np.min(planner.speed_caps_mps - speeds[1:]))
    last_bound = planner.terminal_heading_rad + planner.terminal_heading_per_mps * speeds[-1]
    assert over_plan["terminal_heading"] == pytest.approx(last_bound - abs(states[-1, 1]))
    gentle, hard = decisions[:4], decisions[4:]
    for decision in gentle:  # certified as asked: the drivetrain's command is the agent's
        assert not decision["intervened"] and decision["status"] == "certified"
        np.testing.assert_allclose(decision["filtered_action"], [0.02, 0.3], atol=0.01)
    assert all(d["filtered_action"][0] < 0.45 for d in hard if d["intervened"])
    assert env.steps == len(decisions)
    assert env.interventions == sum(d["intervened"] for d in decisions) >= 4
    assert env.fallbacks == sum(bool(d["fallback"]) for d in decisions)
    env.close()


def test_a_failed_solve_brakes_along_the_map_and_steers_back_to_the_line(
    monkeypatch: pytest.MonkeyPatch,
):
    """No plan at all (the QP failed) and no certified tail: the fallback brakes at
    ``FALLBACK_BRAKE_MPS2`` and steers the map's curvature less the believed offset and
    heading; the decision says so, and the filter counts the failure."""
    import math

    from saferace.safety.uncertainty.fallback import FALLBACK_BRAKE_MPS2

    env = PredictiveSafetyFilter(make_env())
    observation, info = env.reset(seed=0, options={"start_s_m": 3.0, "start_speed_mps": 2.0})
    monkeypatch.setattr(env.planner, "plan", lambda *args: (np.zeros(2), False))
    monkeypatch.setattr(type(env.planner), "plan_slacks", property(lambda planner: None))
    off_line = {**info, "e_y_m": 0.1, "e_psi_rad": 0.05}
    decision = env.certify(observation, off_line, np.array([0.3, 2.0]))
    kappa = env.unwrapped.track.centerline.curvature_scalar(3.0)
    feedforward = math.atan(env.unwrapped.params.wheelbase_m * kappa)
    assert decision.fallback == "solver" and decision.status == "failed"
    assert decision.filtered_action == pytest.approx(
        [feedforward - 0.1 - 0.05, -FALLBACK_BRAKE_MPS2]
    )
    assert all(math.isnan(value) for value in decision.slacks.values())
    assert (env.failures, env.fallbacks, env.interventions) == (1, 1, 1)
    env.close()


def test_the_horizon_needs_two_stages_and_the_plan_is_that_long():
    with pytest.raises(ValueError, match="at least 2 stages"):
        PredictiveSafetyFilter(make_env(), horizon=1)
    env = PredictiveSafetyFilter(make_env(), horizon=2)
    observation, info = env.reset(seed=0, options={"start_speed_mps": 1.0})
    env.certify(observation, info, np.array([0.0, 0.0]))
    assert env.planner.plan_states is not None and len(env.planner.plan_states) == 3
    env.close()


def test_the_planner_gets_the_action_and_its_box_in_the_models_units_and_the_car_the_inverse():
    """The model's acceleration is the drivetrain's command times its gain, less the drag at
    the car's speed (the identified car: a gain below 1 and some drag); the certified first
    input goes back the inverse way."""
    env = PredictiveSafetyFilter(make_env())
    observation, info = env.reset(seed=0, options={"start_speed_mps": 2.0})
    calls = []
    plan = env.planner.plan
    env.planner.plan = lambda *args: calls.append(args) or plan(*args)
    action = np.array([0.05, 1.0])
    decision = env.certify(observation, info, action)
    [(_, _, _, nominal, _, (lower, upper), *_)] = calls
    gain = env.vehicle_params.accel_gain
    drag_mps2 = env.vehicle_params.drag_per_s * float(observation["velocity"][0])
    assert gain < 0.99 and drag_mps2 > 0.05  # the mapping matters on this car

    def model_units(command: np.ndarray) -> list[float]:
        return [command[0], gain * command[1] - drag_mps2]

    assert nominal == pytest.approx(model_units(action))
    box = env._action_box(float(observation["velocity"][0]), float(action[1]))
    assert lower == pytest.approx(model_units(box[0]))
    assert upper == pytest.approx(model_units(box[1]))
    assert decision.status == "certified"
    first = env.planner.plan_inputs[0]
    assert decision.filtered_action == pytest.approx(
        np.clip([first[0], (first[1] + drag_mps2) / gain], env.lower, env.upper)
    )
    env.close()


@pytest.mark.parametrize("half_m", [0.0, 0.1])
def test_the_tail_is_followed_where_the_interval_may_hold_the_car_the_plan_expects(half_m: float):
    """A plan certified 20 cm left of the centre; then, far too fast for any plan, the car
    is believed 8 cm further left than the plan expects: beyond the 5 cm tolerance alone (a
    new, least-violating plan), within it once the interval's 10 cm half width widens it
    (the tail's next input)."""
    env = PredictiveSafetyFilter(
        make_env(), state_source=TruthInABox([half_m, 0.0, 0.0]), uncertainty="robust"
    )
    observation, info = env.reset(seed=0, options={"start_speed_mps": 2.0})
    left = {**info, "e_y_m": 0.2}
    assert env.certify(observation, left, np.array([0.0, 1.0])).status == "certified"
    expected, tail = env.planner.plan_states, env._tail_inputs.copy()
    too_fast = {**observation, "velocity": np.array([9.0, 0.0, 0.0], dtype=np.float32)}
    off_plan = {**left, "e_y_m": float(expected[1, 0]) + 0.08, "e_psi_rad": float(expected[1, 1])}
    decision = env.certify(too_fast, off_plan, np.array([0.0, 1.0]))
    assert decision.fallback == "infeasible"
    box = env._action_box(9.0, -np.inf)  # what any input is held to at that speed
    on_tail = decision.filtered_action == pytest.approx(np.clip(tail[0], *box))
    assert on_tail == (half_m > 0.0), (decision.filtered_action, tail[0])
    env.close()


def test_a_braking_plan_tightens_the_lane_for_the_heading_at_its_first_speed(
    hairpin_track: str,
):
    """A heading known to +-0.3 rad tightens each stage's lane by ``sin(0.3)`` times the
    way driven before the next estimate corrects it, at the speed the car has now (the
    plan brakes for the hairpin: at its last stage's speed the lane tightens up to 6 cm
    less), plus the model's error per second; worked from the plan's own arc lengths."""
    env = PredictiveSafetyFilter(
        make_env(hairpin_track), state_source=TruthInABox([0.0, 0.3, 0.0]), uncertainty="robust"
    )
    observation, info = env.reset(seed=0, options={"start_s_m": 8.0, "start_speed_mps": 4.0})
    for _ in range(3):
        observation, _, _, _, info = env.step(np.zeros(2))
    env.certify(observation, info, np.zeros(2))
    planner = env.planner
    env.close()
    ahead_m = planner.plan_arc_lengths[1:] - planner.plan_arc_lengths[0]
    assert ahead_m[-1] - ahead_m[-2] < 0.8 * ahead_m[0]  # the plan brakes
    speed = float(observation["velocity"][0])
    stage_s = planner.settings.dt_s * np.arange(1, len(ahead_m) + 1)
    expected = np.sin(0.3) * np.minimum(ahead_m, 0.2 * speed) + 0.05 * stage_s
    np.testing.assert_allclose(planner.tightening_m, expected, atol=1e-9)


@pytest.mark.parametrize("driver", ["speeding", "expert"])
def test_the_predictive_filter_keeps_its_distance_to_a_braking_car_ahead(driver: str):
    """Its plan has no cars: the following barrier's bound on the acceleration keeps the
    driver off the filter protocol's braking car on lab (the speeding driver ran into it
    without the bound)."""
    spec = FilterRunSpec(driver, "lab", "true", "braking")
    row = drive_filter_run(FilterEntry("mpsf"), spec, load_filter_suite())
    assert row["at_fault_collisions"] == 0 and row["time_outside_lane_s"] == 0.0
    assert row["completion"] == 1.0
