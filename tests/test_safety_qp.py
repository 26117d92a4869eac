"""The filter QP: agreement with cvxpy, the cone solved two ways, and the chance tightening."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.stats

from saferace.safety.cbf.chance import (
    confidence_quantile,
    constraint_statistics,
    constraint_std,
    spread_at_accel,
    tightening,
)
from saferace.safety.cbf.exact_penalty import solve_filter_qp_l1
from saferace.safety.cbf.qp import FilterProblem, solve_filter_qp, solve_filter_qp_linearised
from saferace.safety.cbf.reference_qp import solve_with_cvxpy

LOWER, UPPER = np.array([-0.36, -4.0]), np.array([0.36, 4.0])


def random_problem(rng: np.random.Generator, chance: bool, k_err: float) -> FilterProblem:
    """Four constraints from 20 perturbed samples, scaled like the lane/heading HOCBFs."""
    n = 20
    spread = rng.uniform(0.0, 0.5)
    a = rng.normal(size=(1, 4, 2)) * [5.0, 0.5] + rng.normal(size=(n, 4, 2)) * spread
    b = rng.normal(size=(1, 4)) * 2.0 + rng.normal(size=(n, 4)) * spread
    statistics = constraint_statistics(a, b)
    return FilterProblem(
        u_mean=rng.uniform(LOWER, UPPER) * 1.2,  # sometimes outside the actuator box
        u_std=np.array([0.1, 1.0]),
        a=statistics.a_mean,
        b=statistics.b_mean,
        lower=LOWER,
        upper=UPPER,
        k_err=k_err,
        covariance=statistics.covariance if chance else None,
        z=confidence_quantile(0.95),
    )


def cvxpy_solution(problem: FilterProblem) -> np.ndarray:
    import cvxpy as cp

    u, status = solve_with_cvxpy(problem)
    assert status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE)
    return u


@pytest.mark.parametrize("chance", [False, True], ids=["deterministic", "chance"])
def test_filter_qp_agrees_with_cvxpy(chance: bool):
    rng = np.random.default_rng(5)
    active = 0
    for trial in range(40):
        problem = random_problem(rng, chance, k_err=[1e2, 1e3, 1e4][trial % 3])
        solution = solve_filter_qp(problem)
        assert solution.solved
        np.testing.assert_allclose(solution.u, cvxpy_solution(problem), atol=1e-5)
        active += not np.allclose(solution.u, np.clip(problem.u_mean, LOWER, UPPER))
    assert active >= 20  # most trials must bend the nominal control, or nothing was tested


def test_slack_is_what_the_constraints_need():
    rng = np.random.default_rng(8)
    problem = random_problem(rng, chance=False, k_err=1e3)
    solution = solve_filter_qp(problem)
    violation = problem.a @ solution.u - problem.b
    np.testing.assert_allclose(solution.slack, np.maximum(violation, 0.0), atol=1e-12)


def test_cone_exact_and_by_iterated_linearisation_agree():
    rng = np.random.default_rng(3)
    for _ in range(30):
        problem = random_problem(rng, chance=True, k_err=1e3)
        exact = solve_filter_qp(problem)
        iterated = solve_filter_qp_linearised(problem)
        assert exact.solved and iterated.solved
        np.testing.assert_allclose(iterated.u, exact.u, atol=1e-6)


def test_tightening_grows_with_spread_and_eta():
    rng = np.random.default_rng(4)
    base_a = rng.normal(size=(1, 4, 2))
    base_b = rng.normal(size=(1, 4))
    noise_a, noise_b = rng.normal(size=(50, 4, 2)), rng.normal(size=(50, 4))
    u = np.array([0.1, 1.0])
    previous = np.zeros(4)
    for spread in (0.01, 0.1, 0.5, 1.0):
        statistics = constraint_statistics(base_a + spread * noise_a, base_b + spread * noise_b)
        current = tightening(statistics, u, 0.95)
        assert np.all(current > previous)
        previous = current
    by_eta = [tightening(statistics, u, eta) for eta in (0.5, 0.8, 0.95, 0.99)]
    assert np.all(by_eta[0] == 0.0)
    assert all(np.all(lo < hi) for lo, hi in itertools.pairwise(by_eta))
    with pytest.raises(ValueError, match="eta"):
        confidence_quantile(1.0)


def test_chance_constraint_holds_with_the_requested_probability():
    """Draw the constraint's coefficients from the fitted Gaussian: Pr(a u <= b) >= eta."""
    rng = np.random.default_rng(6)
    a = np.array([[[4.0, 0.3]]]) + rng.normal(size=(400, 1, 2)) * [0.8, 0.05]
    b = np.array([[0.2]]) + rng.normal(size=(400, 1)) * 0.3
    statistics = constraint_statistics(a, b)
    problem = FilterProblem(
        u_mean=np.array([0.3, 2.0]),
        u_std=np.array([0.1, 1.0]),
        a=statistics.a_mean,
        b=statistics.b_mean,
        lower=LOWER,
        upper=UPPER,
        k_err=1e6,
        covariance=statistics.covariance,
        z=confidence_quantile(0.95),
    )
    u = solve_filter_qp(problem).u
    d = rng.multivariate_normal(np.append(statistics.a_mean[0], statistics.b_mean[0]),
                                statistics.covariance[0], size=200_000)  # fmt: skip
    holds = np.mean(d[:, :2] @ u <= d[:, 2])
    assert holds == pytest.approx(0.95, abs=0.01)
    assert constraint_std(statistics, u)[0] > 0.0
    # the fit is numpy's own mean and (biased) covariance of the samples
    samples = np.column_stack([a[:, 0, :], b[:, 0]])
    np.testing.assert_allclose(statistics.a_mean[0], samples[:, :2].mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(
        statistics.covariance[0], np.cov(samples, rowvar=False, bias=True), atol=1e-12
    )
    # and against the Gaussian the samples came from (not the fit): a u - b is normal with
    # mean 4 u_0 + 0.3 u_1 - 0.2 and variance (0.8 u_0)^2 + (0.05 u_1)^2 + 0.3^2
    mean = 4.0 * u[0] + 0.3 * u[1] - 0.2
    std = np.sqrt((0.8 * u[0]) ** 2 + (0.05 * u[1]) ** 2 + 0.3**2)
    assert scipy.stats.norm.cdf(-mean / std) == pytest.approx(0.95, abs=0.02)


def test_the_spread_at_a_fixed_acceleration_keeps_the_mean():
    """Same mean constraint everywhere; the spread at any ``u`` is the one at ``[u_steer, a]``."""
    rng = np.random.default_rng(7)
    a = rng.normal(size=(12, 4, 2)) * [5.0, 0.5]
    b = rng.normal(size=(12, 4)) * 2.0
    exact = constraint_statistics(a, b)
    fixed = constraint_statistics(*spread_at_accel(a, b, -1.5))
    np.testing.assert_allclose(fixed.a_mean, exact.a_mean, atol=1e-12)
    np.testing.assert_allclose(fixed.b_mean, exact.b_mean, atol=1e-12)
    for steer, accel in ((0.2, 3.0), (-0.1, -4.0), (0.0, -1.5)):
        np.testing.assert_allclose(
            constraint_std(fixed, np.array([steer, accel])),
            constraint_std(exact, np.array([steer, -1.5])),
            atol=1e-12,
        )
    assert not np.allclose(
        constraint_std(exact, np.array([0.2, 3.0])), constraint_std(exact, np.array([0.2, -1.5]))
    )


def test_invalid_problems_are_refused_or_flagged():
    rng = np.random.default_rng(1)
    problem = random_problem(rng, chance=False, k_err=1e3)
    with pytest.raises(ValueError, match="u_std"):
        FilterProblem(**{**problem.__dict__, "u_std": np.array([0.0, 1.0])})
    broken = FilterProblem(**{**problem.__dict__, "b": np.array([np.nan, 0.0, 0.0, 0.0])})
    assert solve_filter_qp(broken).status == "non_finite"


def test_nearly_parallel_constraints_with_a_large_slack_weight():
    """Lane and heading rows of the paper's model nearly parallel, k_err = 1e6: Newton steps
    crawl along the narrow valley; the active-set rescue must still find the minimum."""
    problem = FilterProblem(
        u_mean=np.array([-0.10137272, -0.51108116]),
        u_std=np.array([0.1, 1.0]),
        a=np.array([[1525.75656, 0.471098644], [-1525.75656, -0.471098644],
                     [717.810364, 0.216556039], [-717.810364, -0.216556039]]),
        b=np.array([-165.58165895, 176.51915895, -75.00000766, 84.81748471]),
        lower=np.array([-1e4, -4.0]),
        upper=np.array([1e4, 4.0]),
        k_err=1e6,
    )  # fmt: skip
    solution = solve_filter_qp(problem)
    assert solution.solved and solution.slack.max() < 1e-6
    np.testing.assert_allclose(solution.u, cvxpy_solution(problem), atol=1e-5)


def test_the_l1_slack_agrees_with_cvxpy_and_holds_what_can_hold():
    rng = np.random.default_rng(17)
    exact = held = 0
    for trial in range(60):
        problem = random_problem(rng, chance=trial % 2 == 1, k_err=[1e2, 1e3, 1e4][trial % 3])
        solution = solve_filter_qp_l1(problem)
        assert solution.solved
        reference, status = solve_with_cvxpy(problem, slack_penalty="l1")
        assert status in ("optimal", "optimal_inaccurate")
        np.testing.assert_allclose(solution.u, reference, atol=1e-5)
        if solution.slack.max() < 1e-9:  # everything holds: the hard constraints' optimum,
            exact += 1  # where the squared penalty lets each active constraint give a little
            held += solve_filter_qp(problem).slack.max() > 1e-7
    assert exact >= 10 and held >= 5
