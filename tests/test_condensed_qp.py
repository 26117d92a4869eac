"""The predictive filter's plan, condensed to its inputs and solved by DAQP, against the
sparse QP it stands for solved to high accuracy by Clarabel: the same plan where the
lane's, the speed caps' and the terminal heading's soft rows bind, where uncertainty
tightens the lane past itself, and with the first input weighed as the agent's spread
says."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cvxpy as cp
import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.safety.predictive.filter import PredictiveSafetyFilter
from saferace.safety.stage_qp import StageQP
from saferace.track.random_track import write_random_track


def reference_solution(planner, qp: StageQP) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """States, inputs and slacks of the sparse form of ``qp``, by Clarabel."""
    P, q, A, lo, hi = planner.sparse_problem(qp)
    upper = P.toarray()
    full = upper + np.triu(upper, 1).T
    z = cp.Variable(len(q))
    rows = A.toarray()
    above, below = np.isfinite(lo), np.isfinite(hi)
    problem = cp.Problem(
        cp.Minimize(0.5 * cp.quad_form(z, cp.psd_wrap(full)) + q @ z),
        [rows[above] @ z >= lo[above], rows[below] @ z <= hi[below]],
    )
    problem.solve(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11)
    assert problem.status == cp.OPTIMAL
    N, n, m = qp.B.shape
    value = np.asarray(z.value)
    states, inputs = value[: N * n].reshape(N, n), value[N * n : N * (n + m)].reshape(N, m)
    return states, inputs, value[N * (n + m) :]


def planned(env: PredictiveSafetyFilter, *plan_args) -> tuple[StageQP, tuple[np.ndarray, ...]]:
    """The last QP a plan solved, and the condensed solution the planner kept."""
    planner = env.planner
    solved: list[StageQP] = []
    original = planner._solve_qp

    def capture(qp: StageQP):
        solved.append(qp)
        return original(qp)

    planner._solve_qp = capture
    planner.plan(*plan_args)
    assert planner.plan_states is not None and planner.plan_slacks is not None
    slacks = np.concatenate([planner.plan_slacks["lane"], planner.plan_slacks["speed"],
                             [planner.plan_slacks["heading"]]])  # fmt: skip
    return solved[-1], (planner.plan_states[1:], planner.plan_inputs, slacks)


@pytest.fixture(params=["CenterLine", "RacingLine", "lopsided"])
def env(request: pytest.FixtureRequest, tmp_path: Path):
    """The filter on lab's centre line; on its racing line, whose reference lies off the
    centre line (the cost's reference then matters); and on a random track whose lane is
    up to 16 cm wider on one side near the start (a lane tightened past itself then has
    its middle off the centre line)."""
    track = "lab"
    if request.param == "lopsided":
        track = str(write_random_track(tmp_path / "random_11.csv", 11))
    task = f"saferace/{'RacingLine' if request.param == 'RacingLine' else 'CenterLine'}-v0"
    env = PredictiveSafetyFilter(gym.make(task, track=track, max_laps=1))
    env.reset(seed=0, options={"start_s_m": 2.0, "start_speed_mps": 5.0})
    yield env
    env.close()


def state(env, e_y_m: float, e_psi_rad: float, speed_mps: float) -> np.ndarray:
    return np.append(env.planner.model.state_from(e_y_m, e_psi_rad, speed_mps), 0.0)


CASES = {
    # heading for the left edge at 5 m/s, target full left and speeding up: lane and speed
    # rows bind, and the terminal heading's
    "lane and speed bind": dict(x=(0.3, 0.6, 5.0), target=(0.4, 3.0), margin=(0.0, 0.0)),
    # heading 1.3 rad off the lane at 4 m/s, target full lock further: the terminal
    # heading's row binds, on the left and (its other row) on the right
    "heading binds left": dict(x=(0.0, 1.3, 4.0), target=(0.5, 0.0), margin=(0.0, 0.0)),
    "heading binds right": dict(x=(0.0, -1.3, 4.0), target=(-0.5, 0.0), margin=(0.0, 0.0)),
    # 0.7 m either side of a lane about 1 m wide: the lane's bounds cross
    "lane tightened past itself": dict(x=(0.1, 0.0, 3.0), target=(0.0, 0.0), margin=(0.7, 0.0)),
    # braking hard at 0.1 m/s: the plan stops, and no stage's speed goes below zero
    "braking to a stop": dict(x=(0.0, 0.0, 0.1), target=(0.0, -4.0), margin=(0.0, 0.0)),
    # nothing binds: the plan takes the target
    "free": dict(x=(0.0, 0.0, 2.0), target=(0.05, 0.5), margin=(0.0, 0.0)),
}


def condensed_against_sparse(env, setup: dict, weight) -> tuple[StageQP, np.ndarray, ...]:
    """The plan for ``setup`` (its first steering ``held`` where it says, from its
    ``previous`` one), its condensed solution checked against the sparse QP's: that QP,
    and the sparse solution's states, inputs and slacks."""
    bounds = (np.array([-0.5, -6.0]), np.array([0.5, 6.0]))
    if "held" in setup:
        bounds[0][0] = bounds[1][0] = setup["held"]
    qp, (states, inputs, slacks) = planned(
        env, state(env, *setup["x"]), 2.0, setup.get("previous", 0.0), np.array(setup["target"]),
        np.array(weight), bounds, *setup["margin"],
    )  # fmt: skip
    ref_states, ref_inputs, ref_slacks = reference_solution(env.planner, qp)
    np.testing.assert_allclose(inputs, ref_inputs, atol=1e-4)
    np.testing.assert_allclose(states, ref_states, atol=1e-4)
    np.testing.assert_allclose(slacks, ref_slacks, atol=1e-5)
    return qp, ref_states, ref_inputs, ref_slacks


@pytest.mark.parametrize("case", CASES, ids=list(CASES))
@pytest.mark.parametrize("weight", [(1.0, 1.0), (2500.0, 25.0)], ids=["weight one", "spread"])
def test_the_condensed_plan_is_the_sparse_qps_solution(env, case: str, weight):
    qp, ref_states, _, ref_slacks = condensed_against_sparse(env, CASES[case], weight)
    if case == "lane and speed bind":
        assert ref_slacks.max() > 0.05  # the case is what it says
    if case.startswith("heading binds") and env.track.name == "lab":  # made for lab's bend
        assert ref_slacks[-1] > 0.01
    if case == "lane tightened past itself":
        assert np.all(qp.lane_lower > qp.lane_upper) and ref_slacks[:20].min() > 0.1
    if case == "braking to a stop":
        assert ref_states[:, env.planner.model.speed_index].min() == pytest.approx(0.0, abs=1e-6)
    if case == "free":
        assert ref_slacks.max() < 1e-6


#: Cases made for lab's first bend (elsewhere they bind elsewhere, or not at all).
LAB_CASES = {
    # 8 m/s where the caps are 3-5 m/s, speeding up: every stage's cap binds, the first and
    # the last too (priced as the terminal heading, not as the lane)
    "speeding": dict(x=(0.0, 0.0, 8.0), target=(0.0, 6.0), margin=(0.0, 0.0)),
    # the wheels at 0.3 rad left and the first input held there, the plan turning right:
    # the steering's change from the first stage to the second binds (0.3 rad a stage)
    "steering rate binds": dict(
        x=(0.1, 0.2, 4.0), target=(0.3, 0.0), margin=(0.0, 0.0), previous=0.3, held=0.3
    ),
}


@pytest.mark.parametrize("case", LAB_CASES, ids=list(LAB_CASES))
@pytest.mark.parametrize("weight", [(1.0, 1.0), (2500.0, 25.0)], ids=["weight one", "spread"])
def test_the_caps_and_the_steering_rate_bind_as_the_sparse_qp_says(case: str, weight):
    env = PredictiveSafetyFilter(gym.make("saferace/CenterLine-v0", track="lab", max_laps=1))
    env.reset(seed=0, options={"start_s_m": 2.0, "start_speed_mps": 5.0})
    _, _, ref_inputs, ref_slacks = condensed_against_sparse(env, LAB_CASES[case], weight)
    env.close()
    N = len(ref_inputs)
    if case == "speeding":
        assert ref_slacks[N : 2 * N].min() > 0.1
    else:
        assert ref_inputs[1, 0] - ref_inputs[0, 0] == pytest.approx(-0.3, abs=1e-6)


@pytest.mark.parametrize("missing", ["speed_caps", "heading_bound"])
def test_the_condensed_plan_refuses_a_qp_without_its_caps_or_heading_bound(env, missing: str):
    bounds = (np.array([-0.5, -6.0]), np.array([0.5, 6.0]))
    qp, _ = planned(
        env, state(env, 0.0, 0.0, 2.0), 2.0, 0.0, np.array([0.05, 0.5]), np.ones(2), bounds,
        0.0, 0.0,
    )  # fmt: skip
    N, _, m = qp.B.shape
    with pytest.raises(ValueError, match="speed caps and a terminal heading bound"):
        env.planner._qp.solve(replace(qp, **{missing: None}), np.eye(N * m))
