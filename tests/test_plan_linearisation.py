"""Where the predictive plan is linearised: each step about the last plan shifted by a
step, again about its own first plan only where that one is not certified."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.safety.ltv_mpc import FrenetMPC
from saferace.safety.predictive.filter import PredictiveSafetyFilter
from saferace.safety.predictive.plan import RELINEARISATIONS


class Solves:
    """Records, for each QP solve of a planner, the inputs it was linearised about and
    the plan's inputs it gave."""

    def __init__(self, planner, monkeypatch: pytest.MonkeyPatch) -> None:
        self.linearised: list[np.ndarray] = []
        self.planned: list[np.ndarray] = []
        linearise, solve = planner._linearisation_trajectory, planner._solve

        def recorded_linearisation(x0, s0):
            x, u = linearise(x0, s0)
            self.linearised.append(u.copy())
            return x, u

        def recorded_solve(x0, s0):
            u = solve(x0, s0)
            self.planned.append(planner.plan_inputs.copy())
            return u

        monkeypatch.setattr(planner, "_linearisation_trajectory", recorded_linearisation)
        monkeypatch.setattr(planner, "_solve", recorded_solve)


def filtered_lab(speed_mps: float) -> tuple[PredictiveSafetyFilter, dict, dict]:
    env = PredictiveSafetyFilter(gym.make("saferace/CenterLine-v0", track="lab", max_laps=1))
    observation, info = env.reset(seed=0, options={"start_speed_mps": speed_mps})
    return env, observation, info


def test_a_step_linearises_about_the_last_plan_shifted_by_one_step(monkeypatch):
    """The first solve of a step starts from the last step's plan moved on a step (its
    second input first, its last held): not the last plan as it was."""
    env, observation, info = filtered_lab(2.0)
    assert env.certify(observation, info, np.array([0.0, 0.5])).status == "certified"
    last = env.planner.plan_inputs.copy()
    solves = Solves(env.planner, monkeypatch)
    observation, _, _, _, info = env.step(np.array([0.0, 0.5]))
    env.close()
    np.testing.assert_array_equal(solves.linearised[0], np.vstack([last[1:], last[-1:]]))
    assert not np.allclose(solves.linearised[0], last)


def test_a_certified_plan_is_solved_once_and_an_uncertified_one_again_about_itself(
    monkeypatch,
):
    """A plan that certifies on the first solve is kept (one solve a step). Far too fast
    for the map no plan certifies: it is solved again, each time linearised about the plan
    the solve before gave."""
    env, observation, info = filtered_lab(2.0)
    env.certify(observation, info, np.array([0.0, 0.5]))
    solves = Solves(env.planner, monkeypatch)
    assert env.certify(observation, info, np.array([0.0, 0.5])).status == "certified"
    assert len(solves.linearised) == len(solves.planned) == 1

    too_fast = {**observation, "velocity": np.array([9.0, 0.0, 0.0], dtype=np.float32)}
    solves = Solves(env.planner, monkeypatch)
    assert env.certify(too_fast, info, np.array([0.0, 1.0])).status == "uncertified"
    env.close()
    assert len(solves.planned) == 1 + RELINEARISATIONS
    for linearised, planned_before in zip(solves.linearised[1:], solves.planned[:-1], strict=True):
        np.testing.assert_array_equal(linearised, planned_before)


def test_a_state_cost_coupling_two_states_of_any_stage_is_refused(monkeypatch):
    """The condensed plan weighs each state on its own: a cost coupling two states is
    refused, the last stage's as the first's."""
    build = FrenetMPC._build

    def coupled(planner) -> None:
        build(planner)
        layout, cost = planner._layout, planner._P.tolil()
        last = layout.x(layout.N - 1)
        cost[last, last + 1] = 1.0
        planner._P = cost.tocsc()

    monkeypatch.setattr(FrenetMPC, "_build", coupled)
    with pytest.raises(ValueError, match="diagonal state cost"):
        PredictiveSafetyFilter(gym.make("saferace/CenterLine-v0", track="lab"))
