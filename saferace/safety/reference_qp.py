"""The filter QP written plainly in cvxpy: the reference its fast solver is checked against."""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from saferace.safety.qp import FilterProblem


def covariance_root(covariance: np.ndarray) -> np.ndarray:
    """``M`` with ``M^T M = covariance`` (symmetric square root; covariances may be singular)."""
    values, vectors = np.linalg.eigh(covariance)
    return (vectors * np.sqrt(np.clip(values, 0.0, None))) @ vectors.T


def filter_qp_problem(problem: FilterProblem) -> tuple[cp.Problem, cp.Variable, cp.Variable]:
    """The paper's QP with explicit slacks and second-order cones, as a cvxpy problem."""
    u = cp.Variable(2)
    slack = cp.Variable(len(problem.b))
    weights = 1.0 / np.asarray(problem.u_std, dtype=float)
    objective = cp.sum_squares(cp.multiply(weights, u - problem.u_mean)) + problem.k_err * (
        cp.sum_squares(slack)
    )
    constraints = [u >= problem.lower, u <= problem.upper]
    c = cp.hstack([u, np.array([-1.0])])
    for j in range(len(problem.b)):
        lhs = problem.a[j] @ u - problem.b[j]
        if problem.covariance is not None and problem.z > 0.0:
            lhs = lhs + problem.z * cp.norm(covariance_root(problem.covariance[j]) @ c)
        constraints.append(lhs <= slack[j])
    return cp.Problem(cp.Minimize(objective), constraints), u, slack


def solve_with_cvxpy(problem: FilterProblem, solver: str = cp.CLARABEL) -> tuple[np.ndarray, str]:
    """The reference minimiser and cvxpy's status."""
    program, u, _ = filter_qp_problem(problem)
    program.solve(solver=solver)
    return np.asarray(u.value, dtype=float), program.status
