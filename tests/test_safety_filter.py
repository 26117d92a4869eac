"""The SafetyFilter: forward invariance, its info, the action spread, fallback, agents."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import sympy as sp

import saferace  # noqa: F401  (registers the tasks)
from saferace.agents.reckless import DriftAgent, WeaveAgent
from saferace.eval.filters import FilterConfig, apply_filter
from saferace.eval.runner import run_episode
from saferace.names import GAIN_NAMES as FILTER_GAINS
from saferace.safety.cbf import filter as filter_module
from saferace.safety.cbf.barriers import (
    BARRIER_NAMES,
    BarrierContext,
    hocbf_condition,
    linearised_constraints,
)
from saferace.safety.cbf.filter import GAIN_PRESETS, SafetyFilter
from saferace.safety.cbf.qp import FilterProblem, FilterSolution, solve_filter_qp
from saferace.safety.decision import NominalAction
from saferace.safety.models import FrenetModel, param_values, symbolic_model
from saferace.safety.uncertainty.fallback import FALLBACK_BRAKE_MPS2
from saferace.safety.uncertainty.state_sources import (
    NoisyOracleStateSource,
    SpreadScaledStateSource,
    true_lane_state,
)
from saferace.safety.vehicle_params import load_params
from saferace.track import Track

LOWER, UPPER = np.array([-0.36, -4.0]), np.array([0.36, 4.0])
UNBOUNDED = np.array([1e3, 1e3])


def psi_functions(model_name: str, context: BarrierContext, params: tuple):
    """``psi_0 .. psi_{m-1}`` of every barrier as numeric functions of (state, control,
    curvature)."""
    model = symbolic_model(model_name)
    values = {
        "w_left": context.w_left_m,
        "w_right": context.w_right_m,
        "half_width": context.half_width_m,
        "theta_max": context.theta_max_rad,
        "lateral_decel": context.lateral_decel_mps2,
        **{f"lam_{i}": gain for i, gain in enumerate(context.gains, start=1)},
        "w_left_slope": context.w_left_slope,
        "w_right_slope": context.w_right_slope,
    }
    substitutions = {
        sp.Symbol(k, **({"positive": True} if k == "lateral_decel" else {"real": True})): v
        for k, v in values.items()
    }
    substitutions.update(dict(zip(model.params, params, strict=True)))
    arguments = (*model.state, *model.control, model.kappa)
    return [
        sp.lambdify(arguments, psi.subs(substitutions), "math")
        for name in BARRIER_NAMES
        for psi in hocbf_condition(model_name, name).psi[:-1]
    ]


@pytest.mark.parametrize(
    ("model_name", "lam", "lateral_decel_mps2"),
    [
        ("kinematic", 2.5, np.inf),  # the paper's class-K functions
        ("kinematic", (8.0, 8.0), 3.0),  # large gains, the lane's first function saturating
        ("kinematic", (20.0, 4.0), 5.0),  # GAIN_PRESETS["tuned"]
        ("dynamic-paper", 2.5, np.inf),
    ],
)
def test_forward_invariance_in_the_pure_model(
    model_name: str, lam: float | tuple[float, ...], lateral_decel_mps2: float
):
    """Random nominal controls from random safe states never leave the safe set.

    The HOCBF theorem assumes the QP stays feasible, so the filtered steering is unbounded
    here (the nominal steering is drawn from the car's actuator box) and the kinematic
    model's tan is linearised at the filtered control itself (three re-linearisations).
    """
    params = load_params()
    values = param_values(params)
    model = FrenetModel(model_name, params)
    context = BarrierContext(0.5, 0.5, 0.15, np.pi / 4, lam, lateral_decel_mps2)
    # Steering unbounded (for tan: within (-pi/2, pi/2)); the acceleration keeps the car's
    # limit, or the 5 ms integration steps would not resolve the speed it commands.
    bound = np.array([1.4 if model_name == "kinematic" else 1e4, 4.0])
    rng = np.random.default_rng(0)
    worst, runs, rejected, acted, steps = np.inf, 0, 0, 0, 0
    psi = psi_functions(model_name, context, values)
    while runs < 20:
        kappa = rng.uniform(-0.3, 0.3)
        speed = rng.uniform(1.0, 4.0)
        x = model.state_from(rng.uniform(-0.35, 0.35), rng.uniform(-0.4, 0.4), speed)
        if min(f(*x, 0.0, 0.0, kappa) for f in psi) < 0.0:
            rejected += 1
            continue  # outside the HOCBF safe set (every psi_i, i < m, non-negative)
        runs += 1
        for _ in range(400):
            # Random steering; random acceleration around holding the initial speed (at a
            # standstill steering loses its authority and the relative degree drops).
            speed_hold = 2.0 * (speed - x[model.speed_index])
            nominal = u = np.array([rng.uniform(-0.36, 0.36), speed_hold + rng.uniform(-2, 2)])
            for _ in range(4):
                a, b, h = linearised_constraints(model_name, values, x, kappa, u, context)
                problem = FilterProblem(
                    nominal, np.array([0.1, 1.0]), a[0], b[0], -bound, bound, 1e6
                )
                solution = solve_filter_qp(problem)
                u = solution.u
            assert solution.solved and solution.slack.max() < 1e-4  # soft by O(1/k_err)
            acted += bool(np.any(np.abs(u - nominal) > 1e-3))
            steps += 1
            worst = min(worst, h.min())
            x = model.step(x, u, kappa, 0.005)
    assert rejected > 0  # the sampling reaches beyond the safe set, so the check is real
    assert acted > 0.05 * steps  # the random controls needed the filter, often
    assert worst > -1e-3  # only the sampling of a continuous-time condition


def make_env(track: str = "lab", **kwargs) -> gym.Env:
    return gym.make("saferace/CenterLine-v0", track=track, max_laps=1, **kwargs)


def test_info_reports_every_step_and_a_nominal_action_inside_is_untouched():
    env = SafetyFilter(make_env())
    _, start = env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([0.0, 0.0]))
    safety = info["safety"]
    assert set(safety["barriers"]) == {*BARRIER_NAMES, "speed"}
    assert not safety["intervened"] and safety["status"] == "solved"
    assert safety["filtered_action"] == pytest.approx([0.0, 0.0], abs=1e-6)
    # the lane barrier at the state it was computed in: edge - offset - half width - margin
    assert safety["barriers"]["lane_left"] == pytest.approx(
        start["w_left_m"] - start["e_y_m"] - 0.15 - 0.05, abs=1e-6
    )
    # Hard left towards the lane's edge: unfiltered the car leaves the lane; filtered it
    # stays, and the filter says it steered back.
    options = {"start_s_m": 1.0, "start_speed_mps": 3.0}
    unfiltered = make_env()
    unfiltered.reset(seed=0, options=options)
    costs = [unfiltered.step(np.array([0.36, 0.0]))[4]["cost"] for _ in range(15)]
    unfiltered.close()
    assert max(costs) > 0.0
    _, info = env.reset(seed=0, options=options)
    for _ in range(15):
        _, _, _, _, info = env.step(np.array([0.36, 0.0]))
        assert info["cost"] == 0.0
    assert info["safety"]["intervened"]
    assert info["safety"]["filtered_action"][0] < 0.36
    env.close()


def test_the_less_certain_control_is_bent_more():
    env = SafetyFilter(make_env())
    observation, info = env.reset(seed=0)
    for _ in range(10):
        observation, _, _, _, info = env.step(np.array([0.36, 0.0]))
    unsure_steer = env.certify(observation, info, np.array([0.36, 2.0]), np.array([1.0, 0.2]))
    unsure_accel = env.certify(observation, info, np.array([0.36, 2.0]), np.array([0.02, 5.0]))
    steer_change = abs(unsure_steer.filtered_action[0] - 0.36)
    assert steer_change > abs(unsure_accel.filtered_action[0] - 0.36)
    _, _, _, _, info = env.step(NominalAction(np.array([0.36, 2.0]), np.array([1.0, 0.2])))
    assert info["safety"]["intervened"]
    env.close()


def test_failed_solves_fall_back_to_braking_toward_the_center(monkeypatch):
    def failing(problem):
        return FilterSolution(problem.u_mean, np.zeros(len(problem.b)), "max_iterations", 60)

    monkeypatch.setattr(filter_module, "solve_filter_qp", failing)
    env = SafetyFilter(make_env())
    env.reset(seed=0, options={"start_s_m": 2.0})
    for _ in range(3):
        _, _, _, _, info = env.step(np.array([0.3, 3.0]))
    safety = info["safety"]
    assert safety["fallback"] == "solver" and safety["status"] == "max_iterations"
    assert safety["filtered_action"][1] == pytest.approx(-FALLBACK_BRAKE_MPS2)
    assert np.sign(safety["filtered_action"][0]) == -np.sign(info["e_y_m"] + info["e_psi_rad"])
    assert env.failures == 3
    env.close()


def test_steering_is_bounded_to_the_tyres_grip():
    """``|tan delta| <= a_max L / v^2``: less steering the faster the car."""
    tuned = GAIN_PRESETS["tuned"]  # the lane barriers leave the steering free enough to bind
    bounded = SafetyFilter(make_env(), max_lateral_accel_mps2=2.0, **tuned)
    free = SafetyFilter(make_env(), **tuned)
    clipped = 0
    for speed in (1.0, 4.0, 6.0):
        options = {"start_speed_mps": speed}
        observation, info = bounded.reset(seed=0, options=options)
        free.reset(seed=0, options=options)
        nominal = np.array([0.36, 0.0])
        unbounded_steer = free.certify(observation, info, nominal).filtered_action[0]
        steer = bounded.certify(observation, info, nominal).filtered_action[0]
        v_x = float(observation["velocity"][0])
        allowed = np.arctan(2.0 * bounded.wheelbase_m / v_x**2)
        assert steer == pytest.approx(min(unbounded_steer, allowed), abs=1e-6)
        clipped += allowed < unbounded_steer
    assert 0 < clipped < 3  # the bound binds at speed only
    bounded.close()
    free.close()


def test_the_filter_brakes_to_a_stop_but_never_reverses():
    """Braking is capped at what stops the car within one control step."""
    env = SafetyFilter(make_env())
    observation, info = env.reset(seed=0, options={"start_speed_mps": 1.0})
    speeds = []
    for _ in range(40):
        v_x = float(observation["velocity"][0])
        observation, _, terminated, truncated, info = env.step(np.array([0.0, -4.0]))
        applied = info["safety"]["filtered_action"][1]
        assert applied == pytest.approx(max(-4.0, -max(v_x, 0.0) / env.control_dt_s))
        speeds.append(float(observation["velocity"][0]))
        assert not (terminated or truncated)
    assert min(speeds) > -0.05
    assert speeds[-1] < 0.05  # it did stop
    env.close()


def test_a_stopped_car_heading_for_the_edge_creeps_away_on_full_lock():
    """At a standstill the steering drops out of the lane barrier, and accelerating heads
    for the edge: without the creep rule the filter holds the car there for good."""
    held, creeping = (SafetyFilter(make_env(), creep_speed_mps=speed) for speed in (0.0, 0.5))
    decisions = {}
    for name, env in (("held", held), ("creeping", creeping)):
        observation, info = env.reset(seed=0, options={"start_speed_mps": 0.0})
        observation = {**observation, "velocity": np.zeros(3, dtype=np.float32)}
        info = {**info, "e_y_m": 0.2, "e_psi_rad": 0.2}  # on the barrier, heading out
        decisions[name] = env.certify(observation, info, np.array([-0.1, 4.0])).filtered_action
        if name == "creeping":  # an agent that brakes is not made to creep
            braking = env.certify(observation, info, np.array([-0.1, -1.0])).filtered_action
            assert braking[1] == pytest.approx(0.0, abs=1e-6)  # no braking past standstill
        env.close()
    assert decisions["held"][1] == pytest.approx(0.0, abs=1e-3)
    assert decisions["creeping"][1] == pytest.approx(filter_module.CREEP_ACCEL_MPS2)
    assert decisions["creeping"][0] == pytest.approx(-0.36)  # full lock away from the edge


def test_a_failed_solve_brakes_below_the_creep_speed(monkeypatch):
    def failing(problem):
        return FilterSolution(problem.u_mean, np.zeros(len(problem.b)), "max_iterations", 60)

    monkeypatch.setattr(filter_module, "solve_filter_qp", failing)
    env = SafetyFilter(make_env())
    observation, info = env.reset(seed=0, options={"start_speed_mps": 0.3})
    decision = env.certify(observation, info, np.array([0.0, 4.0]))
    assert decision.fallback
    assert decision.filtered_action[1] == pytest.approx(-FALLBACK_BRAKE_MPS2)
    env.close()


def test_bad_arguments_are_refused():
    with pytest.raises(KeyError):
        SafetyFilter(make_env(), model="bicycle")
    with pytest.raises(ValueError, match="eta"):
        SafetyFilter(make_env(), eta=0.3)
    with pytest.raises(ValueError, match="lane_margin_m"):
        SafetyFilter(make_env(), lane_margin_m=-0.1)
    with pytest.raises(ValueError, match="class-K gains"):
        SafetyFilter(make_env(), lam=(8.0, -1.0))
    with pytest.raises(ValueError, match="lateral_decel_mps2"):
        SafetyFilter(make_env(), lateral_decel_mps2=0.0)
    with pytest.raises(ValueError, match="creep_speed_mps"):
        SafetyFilter(make_env(), creep_speed_mps=-1.0)
    env = SafetyFilter(make_env())
    with pytest.raises(gym.error.ResetNeeded):
        env.step(np.zeros(2))


def test_gain_presets_reach_the_filter_by_name():
    assert tuple(GAIN_PRESETS) == FILTER_GAINS
    filtered = apply_filter(make_env(), FilterConfig(kind="cbf", gains="tuned"))
    assert filtered.lam == GAIN_PRESETS["tuned"]["lam"]
    assert filtered.lateral_decel_mps2 == GAIN_PRESETS["tuned"]["lateral_decel_mps2"]
    default = apply_filter(make_env(), FilterConfig(kind="cbf"))
    assert default.lam == 2.5  # the paper's gain, with the steering within the tyres' grip
    assert default.max_lateral_accel_mps2 == GAIN_PRESETS["grip"]["max_lateral_accel_mps2"] > 0
    assert (
        apply_filter(make_env(), FilterConfig(kind="cbf", gains="paper")).max_lateral_accel_mps2
        is None
    )
    with pytest.raises(ValueError, match="gains"):
        FilterConfig(kind="cbf", gains="fast")


@pytest.mark.parametrize("gains", list(GAIN_PRESETS))
@pytest.mark.parametrize("agent_class", [DriftAgent, WeaveAgent])
def test_reckless_agents_leave_the_lane_unless_filtered(agent_class, gains: str):
    free = make_env(max_steps=300)
    result = run_episode(free, agent_class.for_env(free), seed=0)
    assert result.summary["time_outside_lane_s"] > 0.0
    filtered = SafetyFilter(make_env(max_steps=300), **GAIN_PRESETS[gains])
    result = run_episode(filtered, agent_class.for_env(filtered), seed=0)
    assert result.summary["time_outside_lane_s"] == 0.0
    assert result.summary["min_lane_barrier_m"] > 0.0
    assert result.summary["intervention_rate"] > 0.3
    free.close()
    filtered.close()


def test_noisy_oracle_samples_spread_and_miss_the_truth_alike():
    source = NoisyOracleStateSource(std=(0.05, 0.05, 0.0), n_samples=20, seed=1)
    info = {"e_y_m": 0.1, "e_psi_rad": -0.2, "kappa_radpm": 0.3}
    draws = np.array([source.samples({}, info) for _ in range(500)])
    errors = draws.mean(axis=1) - [0.1, -0.2, 0.3]
    assert np.std(errors[:, 0]) == pytest.approx(0.05 * np.sqrt(1 + 1 / 20), rel=0.1)
    assert np.mean(np.std(draws[:, :, 0], axis=1)) == pytest.approx(0.05, rel=0.1)
    assert np.all(draws[:, :, 2] == 0.3)


class _ShrunkTowardTheCentre:
    """A state network's failure near the edges: ``e_y`` halved, spread 1 cm."""

    def reset(self, seed=None) -> None:
        self._rng = np.random.default_rng(0)

    def samples(self, observation, info):
        state = true_lane_state(info) * [0.5, 1.0, 1.0]
        return state + self._rng.standard_normal((10, 3)) * [0.01, 0.01, 0.0]


def test_a_widened_spread_keeps_a_centre_biased_belief_inside_the_lane():
    source = _ShrunkTowardTheCentre()
    source.reset()
    widened = SpreadScaledStateSource(source, (10.0, 2.0, 1.0))
    info = {"e_y_m": 0.2, "e_psi_rad": 0.1, "kappa_radpm": 0.5}
    source.reset()
    narrow = source.samples({}, info)
    source.reset()
    wide = widened.samples({}, info)
    assert wide.mean(axis=0) == pytest.approx(narrow.mean(axis=0), abs=1e-12)
    assert wide.std(axis=0) == pytest.approx(narrow.std(axis=0) * [10.0, 2.0, 1.0])
    outside = {}
    for name, state_source in (("narrow", _ShrunkTowardTheCentre()), ("widened", widened)):
        filtered = SafetyFilter(
            make_env(max_steps=300), state_source, map_curvature=True, **GAIN_PRESETS["tuned"]
        )
        result = run_episode(filtered, DriftAgent.for_env(filtered), seed=0)
        outside[name] = result.summary["time_outside_lane_s"]
        filtered.close()
    assert outside["narrow"] > 1.0 and outside["widened"] == 0.0


def test_the_filter_config_widens_the_spread():
    config = FilterConfig(kind="cbf", state_noise=(0.05, 0.05), spread_scale=(3.0, 2.0, 1.0))
    filtered = apply_filter(make_env(), config)
    assert isinstance(filtered.state_source, SpreadScaledStateSource)
    assert isinstance(filtered.state_source.source, NoisyOracleStateSource)
    assert filtered.state_source.scale.tolist() == [3.0, 2.0, 1.0]
    filtered.close()
    with pytest.raises(ValueError, match="spread_scale"):
        FilterConfig(kind="cbf", spread_scale=(1.0, 0.0, 1.0))


class _HeadingSpread:
    """The truth, with the heading spread over +-0.3 rad: a state network unsure of it."""

    def reset(self, seed=None) -> None:
        """Nothing to reset."""

    def samples(self, observation, info):
        samples = np.tile(true_lane_state(info), (9, 1))
        samples[:, 1] += np.linspace(-0.3, 0.3, 9)
        return samples


def test_the_filter_does_not_brake_to_shrink_its_heading_spread():
    """Centred and straight at 3 m/s, neither lane side is feasible for that spread;
    braking from +2 to -4 would narrow the spread by a quarter, but the filter keeps the agent's
    acceleration and leaves the slack (see ``spread_at_accel`` in SafetyFilter)."""
    env = SafetyFilter(make_env(), _HeadingSpread(), map_curvature=True, **GAIN_PRESETS["tuned"])
    observation, info = env.reset(seed=0, options={"start_speed_mps": 3.0})
    decision = env.certify(observation, info, np.array([0.0, 2.0]))
    assert decision.filtered_action == pytest.approx([0.0, 2.0], abs=0.01)
    assert min(decision.slacks["lane_left"], decision.slacks["lane_right"]) > 1.0
    env.close()


class _WrongCurvature:
    """The truth, but with a curvature far from the track's (a state network's worst)."""

    def reset(self, seed=None) -> None:
        """Nothing to reset."""

    def samples(self, observation, info):
        return np.array([[info["e_y_m"], info["e_psi_rad"], -3.0]])


def test_map_curvature_replaces_the_sources_curvature():
    env = gym.make("saferace/CenterLine-v0", track="lab")
    try:
        decisions = {}
        for name, source, from_map in (
            ("oracle", None, False),
            ("wrong", _WrongCurvature(), False),
            ("wrong, map", _WrongCurvature(), True),
        ):
            wrapped = SafetyFilter(env, state_source=source, map_curvature=from_map)
            wrapped.reset(seed=0)
            for _ in range(40):  # into lab's first left-hand bend
                *_, info = wrapped.step([0.25, 1.0])
            decisions[name] = info["safety"]["filtered_action"]
        assert decisions["wrong, map"] == pytest.approx(decisions["oracle"], abs=1e-9)
        assert decisions["wrong"] != pytest.approx(decisions["oracle"], abs=1e-3)
    finally:
        env.close()


@pytest.mark.parametrize("steer_rad", [0.6, -0.6])
def test_relinearising_holds_an_agent_steering_hard_one_way(steer_rad: float):
    """Full steering and throttle, always: linearised at that steering only, the filter's
    constraints promise more turn than the car gets, and it comes closer to the line: its
    lane barrier fell to 1-2 cm here (the line lies 5 cm beyond 0), at least half a
    centimetre lower than re-linearised."""
    summaries = {}
    for passes in (1, 2):
        filtered = SafetyFilter(
            make_env(max_steps=300), linearisation_passes=passes, **GAIN_PRESETS["tuned"]
        )
        summaries[passes] = run_episode(
            filtered, lambda observation, info: np.array([steer_rad, 4.0]), seed=0
        ).summary
        filtered.close()
    assert summaries[1]["min_lane_barrier_m"] < summaries[2]["min_lane_barrier_m"] - 0.005
    assert summaries[2]["time_outside_lane_s"] == 0.0
    assert summaries[2]["min_lane_barrier_m"] > 0.0


def test_the_lane_barriers_preview_the_narrowest_width_ahead():
    """``width_preview_s``: the barrier is measured to the narrowest edge the car reaches
    within that time, so a narrowing is met before the car is in it."""
    angle = np.linspace(0.0, 2.0 * np.pi, 200, endpoint=False)
    narrow = (angle > np.pi) & (angle < np.pi + 0.5)  # 4 m of a 0.6 m left half width
    track = Track.from_arrays(
        8.0 * np.cos(angle), 8.0 * np.sin(angle), 1.0, np.where(narrow, 0.6, 1.0), name="dent"
    )
    plain = SafetyFilter(make_env(track))
    previewing = SafetyFilter(make_env(track), width_preview_s=0.5)
    for env in (plain, previewing):
        observation, info = env.reset(seed=0, options={"start_s_m": 24.0, "start_speed_mps": 3.0})
        decision = env.certify(observation, info, np.zeros(2))
        ahead = info["s_m"] + np.linspace(0.0, 0.5 * observation["velocity"][0], 200)
        w_left = track.widths(ahead)[1].min() if env is previewing else info["w_left_m"]
        expected = w_left - info["e_y_m"] - env.half_width_m
        assert decision.barriers["lane_left"] == pytest.approx(expected, abs=2e-3)
    assert previewing.certify(observation, info, np.zeros(2)).barriers["lane_left"] < (
        plain.certify(observation, info, np.zeros(2)).barriers["lane_left"] - 0.1
    )
    with pytest.raises(ValueError, match="width_preview_s"):
        SafetyFilter(make_env(), width_preview_s=-1.0)


def test_the_l1_slack_holds_the_barriers_exactly_where_the_squared_one_gives_a_little():
    """The drift agent behind either slack: both keep it inside; on the steps the filter bent,
    the squared slack leaves its active barriers a sliver of violation, the L1 one none."""
    slivers = {}
    for slack in ("squared", "l1"):
        env = apply_filter(make_env(max_steps=300), FilterConfig(kind="cbf", slack=slack))
        agent = DriftAgent.for_env(env)
        observation, info = env.reset(seed=0)
        outside, sliver = 0.0, 0
        for _ in range(300):
            observation, _, terminated, truncated, info = env.step(agent.act(observation, info))
            outside += info["cost"]
            slack_needed = max(info["safety"]["slacks"].values())
            sliver += info["safety"]["intervened"] and 1e-9 < slack_needed < 1e-4
            if terminated or truncated:
                break
        env.close()
        assert outside == 0.0
        slivers[slack] = sliver
    assert slivers["squared"] > 10 and slivers["l1"] == 0
    with pytest.raises(ValueError, match="slack"):
        FilterConfig(kind="cbf", slack="huber")
    assert FilterConfig(kind="cbf", slack="l1").label == "oracle-l1"
