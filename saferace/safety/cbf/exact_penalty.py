"""The safety filter's QP with an exact (L1) penalty on its slacks, solved with Clarabel.

    min_u  (u - u_mean)^T diag(u_std^2)^-1 (u - u_mean) + k_err * sum_j eps_j
    s.t.   a_j^T u - b_j + z sqrt(c(u)^T Sigma_j c(u)) <= eps_j,   eps_j >= 0
           lower <= u <= upper

The squared penalty of :mod:`saferace.safety.cbf.qp` lets every active constraint give a
little (``eps_j = lambda_j / (2 k_err)``) and, when two constraints cannot both hold (both
lane sides), balances their squared violations, which braking can shrink together. The L1
penalty is exact: for ``k_err`` above the constraints' multipliers the solution is the one
of the hard constraints wherever they can hold, and otherwise the smallest summed
violation, with no pull towards balancing them.

Its kinks defeat the squared solver's Newton steps, so the problem is handed whole to an
interior-point conic solver: a QP in ``(v, eps)``, ``v`` the control's deviation in units of
``u_std`` (the scaling of :mod:`saferace.safety.cbf.reference_qp`), each chance constraint a
second-order cone ``z |R c(u)| <= eps_j - a_j^T u + b_j`` with ``R^T R = Sigma_j``.
"""

from __future__ import annotations

import clarabel
import numpy as np
from scipy import sparse

from saferace.safety.cbf.qp import (
    FilterProblem,
    FilterSolution,
    PenaltyObjective,
    failed_solution,
    packaged_solution,
)
from saferace.safety.cbf.reference_qp import covariance_root

#: Clarabel's tolerances: well below the 1e-5 the filter's solvers are checked to.
SOLVER_SETTINGS = {"tol_gap_abs": 1e-10, "tol_gap_rel": 1e-10, "tol_feas": 1e-10}
_SOLVED = {"Solved", "AlmostSolved"}


def solve_filter_qp_l1(problem: FilterProblem) -> FilterSolution:
    """The minimiser of the filter QP with L1 slacks (``iterations``: the solver's)."""
    objective = PenaltyObjective(problem)
    if not objective.finite:
        return failed_solution(problem)
    mean, std = np.asarray(problem.u_mean, float), np.asarray(problem.u_std, float)
    lower, upper = np.asarray(problem.lower, float), np.asarray(problem.upper, float)
    a, b = np.asarray(problem.a, float), np.asarray(problem.b, float)
    count = len(b)
    covariance = problem.covariance if problem.z > 0.0 else None  # None: deterministic
    width = 2 + count
    # the constraints' rows  a_j . (mean + std v) - eps_j <= b_j ; the box ; -eps <= 0
    constraint_rows = np.hstack([a * std, -np.eye(count)])
    box_rows = np.zeros((4, width))
    box_rows[:2, :2], box_rows[2:, :2] = np.eye(2), -np.eye(2)
    slack_rows = np.hstack([np.zeros((count, 2)), -np.eye(count)])
    constraint_bounds = b - a @ mean
    box_bounds = np.concatenate([(upper - mean) / std, (mean - lower) / std, np.zeros(count)])
    bounds: list[np.ndarray]
    if covariance is not None:  # each constraint a cone instead of a row: t = bound - row x >= |w|
        blocks, bounds = [box_rows, slack_rows], [box_bounds]
        for j in range(count):
            root = problem.z * covariance_root(covariance[j])
            spread_rows = np.zeros((3, width))
            spread_rows[:, :2] = -root[:, :2] * std
            blocks += [constraint_rows[j : j + 1], spread_rows]
            bounds += [constraint_bounds[j : j + 1], root @ np.append(mean, -1.0)]
        kinds = [clarabel.NonnegativeConeT(4 + count)] + [clarabel.SecondOrderConeT(4)] * count
    else:
        blocks = [constraint_rows, box_rows, slack_rows]
        bounds = [constraint_bounds, box_bounds]
        kinds = [clarabel.NonnegativeConeT(4 + 2 * count)]
    rows = sparse.csc_matrix(np.vstack(blocks))
    cost = sparse.diags(np.concatenate([[2.0, 2.0], np.zeros(count)]), format="csc")
    linear = np.concatenate([[0.0, 0.0], np.full(count, float(problem.k_err))])
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    for name, value in SOLVER_SETTINGS.items():
        setattr(settings, name, value)
    result = clarabel.DefaultSolver(
        cost, linear, rows, np.concatenate(bounds), kinds, settings
    ).solve()
    solved = str(result.status) in _SOLVED
    u = np.clip(mean + std * np.asarray(result.x[:2]) if solved else mean, lower, upper)
    status = "solved" if solved else "stalled"
    return packaged_solution(objective, [float(u[0]), float(u[1])], status, result.iterations)
