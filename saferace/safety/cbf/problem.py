"""The filter's QP of one linearisation: the lane barriers' rows (their chance constraints'
statistics where sampled) and the speed barrier's row."""

from __future__ import annotations

import numpy as np

from saferace.safety.cbf.barriers import BarrierContext, linearised_constraints
from saferace.safety.cbf.chance import ConstraintStatistics, constraint_statistics, spread_at_accel
from saferace.safety.cbf.qp import FilterProblem


def lane_problem(
    model_name: str,
    param_values: tuple[float, ...],
    states: np.ndarray,
    kappa: np.ndarray,
    linearised_at: np.ndarray,
    context: BarrierContext,
    speed: tuple[np.ndarray, float, float] | None,
    nominal: np.ndarray,
    spread: np.ndarray,
    box: tuple[np.ndarray, np.ndarray],
    k_err: float,
    z: float | None,
) -> tuple[FilterProblem, ConstraintStatistics | None, np.ndarray]:
    """The QP with ``model_name``'s constraints linearised in the steering at
    ``linearised_at`` (``z``: the chance constraints' quantile, ``None``: deterministic),
    the samples' statistics (``None`` if deterministic) and the barrier values. Robust: a
    row per constraint and state point, all of which must hold."""
    lower, upper = box
    chance = z is not None
    a, b, h = linearised_constraints(
        model_name, param_values, states, kappa, linearised_at, context
    )
    if chance:
        a, b = spread_at_accel(a, b, float(np.clip(nominal[1], lower[1], upper[1])))
    statistics = constraint_statistics(a, b) if chance else None
    if statistics is not None:
        a_mean, b_mean, covariance = statistics.a_mean, statistics.b_mean, statistics.covariance
    else:
        a_mean, b_mean, covariance = a.reshape(-1, 2), b.ravel(), None
    if speed is not None:
        speed_row, speed_bound, speed_h = speed
        a_mean = np.vstack([a_mean, speed_row])
        b_mean = np.append(b_mean, speed_bound)
        h = np.column_stack([h, np.full(len(h), speed_h)])
        if covariance is not None:  # measured speed, the samples' lowest limit: no spread
            covariance = np.concatenate([covariance, np.zeros((1, 3, 3))])
    problem = FilterProblem(
        u_mean=nominal, u_std=spread, a=a_mean, b=b_mean, lower=lower, upper=upper,
        k_err=k_err, covariance=covariance, z=z or 0.0,
    )  # fmt: skip
    return problem, statistics, h
