"""One control step's LTV QP in stage form: what each stage's dynamics, costs and bounds are.

:class:`~saferace.safety.ltv_mpc.FrenetMPC` fills one every step; the expert hands it to
OSQP as a sparse QP over states, inputs and slacks, the predictive filter's planner
condenses it to the inputs alone (:mod:`saferace.safety.predictive.condensed_qp`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class StageQP:
    """``x_{k+1} = A_k x_k + B_k u_k + c_k`` from ``x0`` over ``N`` stages (``n`` states,
    the lateral offset first and the heading error second; ``m`` inputs, the steering
    first), with the states' reference and the first input's linear cost, hard bounds
    on the inputs and on the steering's change per stage, and soft bounds on each stage's
    lateral offset (the lane), speed (``speed_caps``, where the QP has them) and the last
    stage's ``|e_psi| - gain v`` (``heading_bound``, where it has one)."""

    x0: np.ndarray  # (n,)
    A: np.ndarray  # (N, n, n)
    B: np.ndarray  # (N, n, m)
    c: np.ndarray  # (N, n)
    reference: np.ndarray  # (N, n): each stage's state reference
    first_input_linear: np.ndarray  # (m,): the first input's linear cost
    input_lower: np.ndarray  # (N, m)
    input_upper: np.ndarray  # (N, m)
    rate_lower: np.ndarray  # (N,): steering change per stage, from the last command
    rate_upper: np.ndarray  # (N,)
    lane_lower: np.ndarray  # (N,)
    lane_upper: np.ndarray  # (N,)
    speed_caps: np.ndarray | None  # (N,)
    heading_bound: float | None

    @property
    def dynamics_offsets(self) -> np.ndarray:
        """``c_k`` with ``A_0 x_0`` added to the first: ``x_1 = B_0 u_0 + offsets[0]``."""
        offsets = self.c.copy()
        offsets[0] += self.A[0] @ self.x0
        return offsets
