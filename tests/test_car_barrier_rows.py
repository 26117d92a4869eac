"""The car barrier's rows in numbers worked by hand, away from the centre line: its widened
superellipse, the following barrier read from the ego's own offset, heading and bend, the
test of a conflict between cars and lane, and the bound the fallbacks keep behind a car."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import sympy as sp

from saferace.safety.cbf.qp import FilterProblem
from saferace.safety.models import FrenetModel, param_values, symbolic_model
from saferace.safety.traffic import car_barriers as cb
from saferace.safety.vehicle_params import load_params

PARAMS = param_values(load_params())
#: The ego 30 cm left of the centre, heading 0.2 rad out, at 3 m/s, in a left bend.
EGO = np.array([0.3, 0.2, 3.0, 0.0])
KAPPA_RADPM = 0.5


def rows(prediction: tuple[float, float, float], widening_m: float = 0.0) -> tuple:
    return cb.car_rows(
        "kinematic", PARAMS, EGO, KAPPA_RADPM, np.zeros(2), [prediction], cb.CAR_GAINS, widening_m
    )


@pytest.mark.parametrize("widening_m", [0.0, 0.15])
def test_the_widened_superellipse_passes_through_both_widened_semi_axes(widening_m: float):
    """``h = 0`` a widened semi-axis ahead of the ego in its line, and one to its side."""
    ahead = rows((-(cb.SEMI_AXIS_S_M + widening_m), EGO[0], 1.0), widening_m)[2][0]
    aside = rows((0.0, EGO[0] - (cb.SEMI_AXIS_Y_M + widening_m), 1.0), widening_m)[2][0]
    assert ahead == pytest.approx(0.0, abs=1e-12) and aside == pytest.approx(0.0, abs=1e-12)


def test_the_following_barrier_reads_the_egos_offset_heading_and_bend():
    """3 m behind a car at 1 m/s in the ego's own line (30 cm left): the ego's speed along
    the track is ``v cos(e_psi) / (1 - kappa e_y)``; a car in the centre line is beside."""
    along_mps = 3.0 * math.cos(0.2) / (1.0 - KAPPA_RADPM * 0.3)
    gap_m = 3.0 - cb.FOLLOW_GAP_M
    h = gap_m - 0.5 * (along_mps**2 / cb.EGO_BRAKE_MPS2 - 1.0 / cb.OPPONENT_ACCEL_MPS2)
    _, b, h_rows = rows((-3.0, 0.3, 1.0))
    assert h_rows[1] == pytest.approx(h)
    bound = cb.EGO_BRAKE_MPS2 * (cb.FOLLOW_GAIN * h / along_mps - 1.0)
    assert b[1] / cb.CAR_ROW_WEIGHT == pytest.approx(bound)
    beside = rows((-3.0, 0.3 - 1.01 * cb.FOLLOW_WIDTH_M, 1.0))[1][1]
    assert beside / cb.CAR_ROW_WEIGHT == cb.UNBOUNDED_ACCEL_MPS2


def problem_with_cars(
    lane_b: list[float], car_b: list[float], a: np.ndarray | None = None
) -> FilterProblem:
    """Lane rows ``lane_b``, then car rows ``car_b`` (superellipse, following, per car),
    each row ``[0, 1] u <= b`` unless ``a`` says otherwise."""
    b = np.array([*lane_b, *car_b])
    return FilterProblem(
        u_mean=np.zeros(2),
        u_std=np.ones(2),
        a=np.tile([0.0, 1.0], (len(b), 1)) if a is None else a,
        b=b,
        lower=np.array([-0.4, -4.0]),
        upper=np.array([0.4, 4.0]),
        k_err=1.0,
    )


def solution(u: list[float], slack: list[float]) -> SimpleNamespace:
    return SimpleNamespace(u=np.array(u), slack=np.array(slack))


SLACK = 1e-4  # the filter's infeasible slack


def test_a_conflict_is_a_car_row_that_needs_slack_or_binds_while_a_lane_row_needs_it():
    problem = problem_with_cars([1.0], [2.0, 100.0])  # one lane row, one car's two
    assert cb.car_conflict(problem, solution([0.0, 0.0], [0.0, 2 * SLACK, 0.0]), 2, 1, SLACK)
    assert not cb.car_conflict(problem, solution([0.0, 0.0], [0.0, SLACK, 0.0]), 2, 1, SLACK)
    # a car row binding (its margin 2 - u_accel below 10 x the slack) while the lane needs slack
    binding = solution([0.0, 2.0 - 0.5 * cb.CAR_ROW_WEIGHT * SLACK], [2 * SLACK, 0.0, 0.0])
    assert cb.car_conflict(problem, binding, 2, 1, SLACK)
    loose = solution([0.0, 2.0 - 2.0 * cb.CAR_ROW_WEIGHT * SLACK], [2 * SLACK, 0.0, 0.0])
    assert not cb.car_conflict(problem, loose, 2, 1, SLACK)  # the car row is not binding
    lane_kept = solution(binding.u, [SLACK, 0.0, 0.0])
    assert not cb.car_conflict(problem, lane_kept, 2, 1, SLACK)  # the lane needs no slack
    # a row's margin is b - a u: the same row pointing the other way does not bind
    flipped = problem_with_cars([1.0], [2.0, 100.0], np.array([[0, 1], [0, -1], [0, 1]]))
    assert not cb.car_conflict(flipped, binding, 2, 1, SLACK)


def test_the_fallbacks_keep_to_the_tightest_following_bound_and_the_action_box():
    weight = cb.CAR_ROW_WEIGHT
    # the lane's last row would cap harder, and is no following row
    problem = problem_with_cars(
        [0.5, weight * -3.0], [weight * -9.0, weight * 1.5, 0.0, weight * -2.0]
    )
    box = (problem.lower, problem.upper)
    assert cb.follow_capped(problem, 4, 3.0, box) == pytest.approx(-2.0)  # the second car's
    assert cb.follow_capped(problem, 4, -3.0, box) == pytest.approx(-3.0)  # already below
    hard = problem_with_cars([0.5], [0.0, weight * -9.0])
    assert cb.follow_capped(hard, 2, 3.0, box) == -4.0  # no harder than the car can brake


def test_the_car_rows_join_a_chance_constrained_problem_with_no_spread_of_their_own():
    lane = problem_with_cars([0.5, 0.7], [])
    lane = FilterProblem(**{**vars(lane), "covariance": np.ones((2, 3, 3))})
    a, b, h = rows((-2.0, 0.3, 1.0))
    joined, values = cb.with_car_rows(lane, np.zeros((5, 2)), (a, b, h))
    assert joined.covariance is not None and joined.covariance.shape == (4, 3, 3)
    assert np.all(joined.covariance[2:] == 0.0) and np.all(joined.covariance[:2] == 1.0)
    np.testing.assert_array_equal(joined.b, [0.5, 0.7, *b])
    assert values.shape == (5, 4) and np.all(values[:, 2:] == h)


def augmented_rk4(model: FrenetModel, z: np.ndarray, u: np.ndarray, a_o: float, h_s: float):
    """One RK4 step of the ego's model state with ``ds`` and the opponent's speed ``v_o``
    appended: ``d(ds)/dt = s_dot - v_o`` in the bend, ``d(v_o)/dt = a_o``."""

    def rate(z: np.ndarray) -> np.ndarray:
        x = z[:-2]
        ds_rate = model.s_dot(x, KAPPA_RADPM) - z[-1]
        return np.array([*model.f(x, u, KAPPA_RADPM), ds_rate, a_o])

    k1 = rate(z)
    k2 = rate(z + 0.5 * h_s * k1)
    k3 = rate(z + 0.5 * h_s * k2)
    k4 = rate(z + h_s * k3)
    return z + h_s * (k1 + 2 * k2 + 2 * k3 + k4) / 6.0


@pytest.mark.parametrize("model_name", ["kinematic", "dynamic"])
@pytest.mark.parametrize("a_o", [0.0, -cb.OPPONENT_ACCEL_MPS2])
def test_each_order_of_the_car_condition_is_the_last_s_rate_along_the_model_in_a_bend(
    model_name: str, a_o: float
):
    """``psi_i = d/dt psi_(i-1) + lam_i psi_(i-1)``, the rate taken numerically along the
    model in a 0.5 1/m bend, 30 cm off the centre line (where the arc length's rate has the
    bend's ``1 / (1 - kappa e_y)``) and closing on an opponent that may brake."""
    model = symbolic_model(model_name)
    numeric = FrenetModel(model_name, load_params())
    axes = (cb.SEMI_AXIS_S_M, cb.SEMI_AXIS_Y_M)
    fixed = {
        model.kappa: KAPPA_RADPM, cb._E_Y_O: 0.1, cb._A_O: a_o,
        cb._AXIS_S: axes[0], cb._AXIS_Y: axes[1],
        **dict(zip(cb._LAMS, cb.CAR_GAINS, strict=True)),
        **dict(zip(model.params, PARAMS, strict=True)),
    }  # fmt: skip
    psi = [
        sp.lambdify((*model.state, *model.control, cb._DS, cb._V_O), p.subs(fixed), "math")
        for p in cb.car_condition(model_name)
    ]
    assert len(psi) == 3  # steering reaches the barrier at its second derivative
    u = np.array([0.1, 0.8])
    x = numeric.state_from(0.3, 0.2, 3.0, 0.1, 0.5)
    z = np.array([*x, -0.6, 1.5])
    step_s = 1e-5  # the dynamic model's yaw rate changes at 50 rad/s^2 here
    ahead, behind = (
        augmented_rk4(numeric, z, u, a_o, step_s),
        augmented_rk4(numeric, z, u, a_o, -step_s),
    )
    for i in (1, 2):
        rate = psi[i - 1](*ahead[:-2], *u, *ahead[-2:]) - psi[i - 1](*behind[:-2], *u, *behind[-2:])
        expected = rate / (2 * step_s) + cb.CAR_GAINS[i - 1] * psi[i - 1](*z[:-2], *u, *z[-2:])
        assert psi[i](*z[:-2], *u, *z[-2:]) == pytest.approx(expected, rel=1e-6)
    final, steer_gradient, accel_gradient, h = cb._car_function(model_name)(
        *x, *u, KAPPA_RADPM, *PARAMS, -0.6, 0.1, 1.5, a_o, *axes, *cb.CAR_GAINS
    )
    assert final == pytest.approx(psi[2](*x, *u, -0.6, 1.5))
    assert h == pytest.approx(psi[0](*x, *u, -0.6, 1.5))
    for gradient, nudge in ((steer_gradient, [1e-6, 0.0]), (accel_gradient, [0.0, 1e-6])):
        change = psi[2](*x, *(u + nudge), -0.6, 1.5) - psi[2](*x, *(u - nudge), -0.6, 1.5)
        assert gradient == pytest.approx(change / 2e-6, rel=1e-5)
