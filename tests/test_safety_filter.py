"""The SafetyFilter wrapper: its info, the action spread, the fallback, reckless agents."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.agents.reckless import DriftAgent, WeaveAgent
from saferace.eval.runner import run_episode
from saferace.safety import filter as filter_module
from saferace.safety.barriers import (
    BARRIER_NAMES,
)
from saferace.safety.filter import NominalAction, SafetyFilter
from saferace.safety.qp import FilterSolution
from saferace.safety.state_sources import NoisyOracleStateSource

LOWER, UPPER = np.array([-0.36, -4.0]), np.array([0.36, 4.0])
UNBOUNDED = np.array([1e3, 1e3])


def make_env(track: str = "lab", **kwargs) -> gym.Env:
    return gym.make("saferace/CenterLine-v0", track=track, max_laps=1, **kwargs)


def test_info_reports_every_step_and_a_nominal_action_inside_is_untouched():
    env = SafetyFilter(make_env())
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([0.0, 0.0]))
    safety = info["safety"]
    assert set(safety["barriers"]) == {*BARRIER_NAMES, "speed"}
    assert not safety["intervened"] and safety["status"] == "solved"
    assert safety["filtered_action"] == pytest.approx([0.0, 0.0], abs=1e-6)
    assert safety["barriers"]["lane_left"] == pytest.approx(
        info["w_left_m"] - 0.15 - 0.05 - 0.0, abs=0.05
    )
    # Hard left at the lane's edge: the filter steers back and says so.
    _, info = env.reset(seed=0, options={"start_s_m": 1.0, "start_speed_mps": 3.0})
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
    assert safety["fallback"] and safety["status"] == "max_iterations"
    assert safety["filtered_action"][1] == pytest.approx(-filter_module.FALLBACK_BRAKE_MPS2)
    assert np.sign(safety["filtered_action"][0]) == -np.sign(info["e_y_m"] + info["e_psi_rad"])
    assert env.failures == 3
    env.close()


def test_bad_arguments_are_refused():
    with pytest.raises(KeyError):
        SafetyFilter(make_env(), model="bicycle")
    with pytest.raises(ValueError, match="eta"):
        SafetyFilter(make_env(), eta=0.3)
    with pytest.raises(ValueError, match="lane_margin_m"):
        SafetyFilter(make_env(), lane_margin_m=-0.1)
    env = SafetyFilter(make_env())
    with pytest.raises(gym.error.ResetNeeded):
        env.step(np.zeros(2))


@pytest.mark.parametrize("agent_class", [DriftAgent, WeaveAgent])
def test_reckless_agents_leave_the_lane_unless_filtered(agent_class):
    free = make_env(max_steps=300)
    result = run_episode(free, agent_class.for_env(free), seed=0)
    assert result.summary["time_outside_lane_s"] > 0.0
    filtered = SafetyFilter(make_env(max_steps=300))
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
