"""A QP in OSQP's form, ``lo <= A x <= hi``, solved by Clarabel with its data updated in place.

The predictive filter's plan (:mod:`saferace.safety.predictive_plan`) weighs its first
input about 1e4 times more than the rest of the plan; OSQP's first-order steps took
thousands of iterations on it (a quarter of the steps hit the iteration limit), where
Clarabel's interior point takes about ten.
"""

from __future__ import annotations

import clarabel
import numpy as np
import scipy.sparse as sp

SOLVED = (clarabel.SolverStatus.Solved, clarabel.SolverStatus.AlmostSolved)


class IntervalQP:
    """``min 1/2 x^T P x + q^T x`` s.t. ``lo <= A x <= hi``, for a fixed sparsity pattern of
    ``A`` (``a_template``) and of the upper triangle of ``P``. A row with ``lo == hi`` is an
    equality; each finite side of the others an inequality. Each solve updates the last
    solver's data while the rows' kinds stay the same, and sets a new one up otherwise."""

    def __init__(self, a_template: sp.csc_matrix, p_template: sp.csc_matrix) -> None:
        self.a_template = a_template
        self.p_template = p_template
        self._solver: clarabel.DefaultSolver | None = None
        self._kinds = b""
        self._entries = self._signs = np.empty(0)

    def solve(
        self,
        p_values: np.ndarray,
        q: np.ndarray,
        a_values: np.ndarray,
        lo: np.ndarray,
        hi: np.ndarray,
    ) -> np.ndarray | None:
        """The minimiser, or None where Clarabel did not solve; ``p_values`` and
        ``a_values`` are the templates' data."""
        equal = lo == hi
        upper, lower = ~equal & np.isfinite(hi), ~equal & np.isfinite(lo)
        kinds = np.concatenate([equal, upper, lower]).tobytes()
        b = np.concatenate([hi[equal], hi[upper], -lo[lower]])
        if self._solver is None or kinds != self._kinds:
            A = self._stack(equal, upper, lower)
            A.data = a_values[self._entries] * self._signs
            P = self.p_template.copy()
            P.data = p_values
            cones = [
                clarabel.ZeroConeT(int(equal.sum())),
                clarabel.NonnegativeConeT(int(upper.sum() + lower.sum())),
            ]
            settings = clarabel.DefaultSettings()
            settings.verbose = False
            settings.presolve_enable = False  # keeps the data updatable
            # Refining each KKT solve to 1e-13 took a third of the time; without it every
            # one of 1218 recorded filter QPs still solved, its first input moved by at most
            # 4e-6 and its slacks by 1e-8.
            settings.iterative_refinement_enable = False
            self._solver = clarabel.DefaultSolver(P, q, A, b, cones, settings)
            self._kinds = kinds
        else:
            self._solver.update(P=p_values, q=q, A=a_values[self._entries] * self._signs, b=b)
        result = self._solver.solve()
        return np.asarray(result.x) if result.status in SOLVED else None

    def _stack(self, equal: np.ndarray, upper: np.ndarray, lower: np.ndarray) -> sp.csc_matrix:
        """The pattern of ``[A_equal; A_upper; -A_lower]``, with where each of its entries
        comes from in ``A``'s data (``_entries``) and its sign (``_signs``)."""
        rows = np.concatenate([np.flatnonzero(equal), np.flatnonzero(upper), np.flatnonzero(lower)])
        sign = np.concatenate([np.ones(equal.sum() + upper.sum()), -np.ones(lower.sum())])
        tracer = self.a_template.copy()
        tracer.data = np.arange(1, tracer.nnz + 1, dtype=float)
        stacked = (sp.diags(sign) @ tracer[rows]).tocsc()
        stacked.sort_indices()
        self._entries = np.abs(stacked.data).astype(int) - 1
        self._signs = np.sign(stacked.data)
        return stacked
