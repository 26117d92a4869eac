"""Chance constraints from state samples (paper Sec. 3.2, corrected in DESIGN.md Sec. 6).

Each sample ``x_i`` of the uncertain state gives a linearised constraint
``a_i^T u <= b_i``. Writing ``d = [a; b]`` and ``c(u) = [u; -1]``, the constraint is
``d^T c(u) <= 0``. With ``d`` Gaussian (mean ``d_mean``, covariance ``Sigma`` fitted to the
samples, normalised by ``n`` as in the paper), ``Pr(d^T c(u) <= 0) >= eta`` is exactly

    a_mean^T u - b_mean + z sqrt(c(u)^T Sigma c(u)) <= 0,    z = Phi^-1(eta),

a second-order cone: the mean constraint tightened by ``z`` standard deviations of its
value at ``u`` (a norm, not the squared norm the paper prints).

:func:`spread_at_accel` fixes the acceleration at which the spread is taken (see
:class:`~saferace.safety.cbf.filter.SafetyFilter` for why the filter takes the agent's).
"""

from __future__ import annotations

from dataclasses import dataclass
from statistics import NormalDist

import numpy as np


@dataclass(frozen=True)
class ConstraintStatistics:
    """Mean and covariance of each constraint's coefficients ``[a_steer, a_accel, b]``."""

    a_mean: np.ndarray  # (B, 2)
    b_mean: np.ndarray  # (B,)
    covariance: np.ndarray  # (B, 3, 3)


def confidence_quantile(eta: float) -> float:
    """``Phi^-1(eta)``; ``eta`` in ``[0.5, 1)`` keeps the chance constraint convex."""
    if not 0.5 <= eta < 1.0:
        raise ValueError(f"eta must be in [0.5, 1), got {eta}")
    return NormalDist().inv_cdf(eta)


def constraint_statistics(a: np.ndarray, b: np.ndarray) -> ConstraintStatistics:
    """Fit a Gaussian to per-sample constraints ``a (n, B, 2)``, ``b (n, B)``."""
    d = np.concatenate([a, b[:, :, None]], axis=2)  # (n, B, 3)
    mean = d.mean(axis=0)
    centred = d - mean
    covariance = np.einsum("nbi,nbj->bij", centred, centred) / len(d)
    return ConstraintStatistics(a_mean=mean[:, :2], b_mean=mean[:, 2], covariance=covariance)


def spread_at_accel(
    a: np.ndarray, b: np.ndarray, accel_mps2: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample constraints ``a (n, B, 2)``, ``b (n, B)`` rewritten so that their mean is
    the same but their spread at any ``u`` is the spread at ``[u_steer, accel_mps2]``: each
    sample's acceleration coefficient is replaced by the samples' mean, and its deviation
    from the mean, times ``accel_mps2``, is moved into ``b``."""
    deviation = a[:, :, 1] - a[:, :, 1].mean(axis=0)
    fixed = a.copy()
    fixed[:, :, 1] -= deviation
    return fixed, b - deviation * accel_mps2


def constraint_std(statistics: ConstraintStatistics, u: np.ndarray) -> np.ndarray:
    """Standard deviation of each constraint's value ``a^T u - b`` at ``u``."""
    c = np.array([u[0], u[1], -1.0])
    return np.sqrt(np.maximum(np.einsum("i,bij,j->b", c, statistics.covariance, c), 0.0))


def tightening(statistics: ConstraintStatistics, u: np.ndarray, eta: float) -> np.ndarray:
    """How much each chance constraint is tighter than its mean at ``u``: ``z * std``."""
    return confidence_quantile(eta) * constraint_std(statistics, u)
