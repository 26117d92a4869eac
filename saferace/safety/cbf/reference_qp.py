"""The filter QP written plainly in cvxpy: the reference its fast solver is checked against."""

from __future__ import annotations

import warnings

import cvxpy as cp
import numpy as np

from saferace.names import SQUARED_SLACK
from saferace.safety.cbf.qp import FilterProblem


def covariance_root(covariance: np.ndarray) -> np.ndarray:
    """``M`` with ``M^T M = covariance`` (symmetric square root; covariances may be singular)."""
    values, vectors = np.linalg.eigh(covariance)
    return (vectors * np.sqrt(np.clip(values, 0.0, None))) @ vectors.T


def filter_qp_problem(
    problem: FilterProblem, slack_penalty: str = SQUARED_SLACK
) -> tuple[cp.Problem, cp.Expression, cp.Variable]:
    """The paper's QP with explicit slacks and second-order cones, as a cvxpy problem
    (``slack_penalty="l1"``: the exact penalty ``k_err * sum(eps)``, ``eps >= 0``).

    The variable is the control's deviation in units of ``u_std`` (``u = u_mean + u_std *
    v``), which keeps the conic solver's problem well scaled; returns the problem, ``u``
    as an expression of ``v``, and the slacks.
    """
    std = np.asarray(problem.u_std, dtype=float)
    v = cp.Variable(2)
    u = problem.u_mean + cp.multiply(std, v)
    slack = cp.Variable(len(problem.b))
    constraints = [u >= problem.lower, u <= problem.upper]
    if slack_penalty == SQUARED_SLACK:
        objective = cp.sum_squares(v) + problem.k_err * cp.sum_squares(slack)
    else:
        objective = cp.sum_squares(v) + problem.k_err * cp.sum(slack)
        constraints.append(slack >= 0.0)
    c = cp.hstack([u, np.array([-1.0])])
    for j in range(len(problem.b)):
        lhs = problem.a[j] @ u - problem.b[j]
        if problem.covariance is not None and problem.z > 0.0:
            lhs = lhs + problem.z * cp.norm(covariance_root(problem.covariance[j]) @ c)
        constraints.append(lhs <= slack[j])
    return cp.Problem(cp.Minimize(objective), constraints), u, slack


#: Clarabel settings tight enough to resolve the flat directions of weakly weighted controls.
CLARABEL_TIGHT = {
    "tol_gap_abs": 1e-12,
    "tol_gap_rel": 1e-12,
    "tol_feas": 1e-12,
    "tol_ktratio": 1e-10,
    "max_iter": 400,
}


def solve_with_cvxpy(
    problem: FilterProblem, tight: bool = True, slack_penalty: str = SQUARED_SLACK
) -> tuple[np.ndarray, str]:
    """The reference minimiser (Clarabel) and cvxpy's status.

    At tight tolerances Clarabel often reports ``optimal_inaccurate``: it stopped at its
    reduced tolerances, which are still far below the 1e-5 the filter is checked to. If
    Clarabel fails at them, it solves again at its defaults.
    """
    program, u, _ = filter_qp_problem(problem, slack_penalty)
    with warnings.catch_warnings():  # the status says it; no need to warn as well
        warnings.filterwarnings("ignore", message="Solution may be inaccurate")
        try:
            program.solve(solver=cp.CLARABEL, **(CLARABEL_TIGHT if tight else {}))
        except cp.error.SolverError:  # too tight for a badly scaled problem: default settings
            program.solve(solver=cp.CLARABEL)
    return np.asarray(u.value, dtype=float), program.status
