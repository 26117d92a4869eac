"""The plan's QP condensed to its inputs and solved by DAQP, a dual active-set solver.

The sparse QP (:class:`~saferace.safety.ltv_mpc.FrenetMPC`) carries every stage's state
and a slack per soft row: 241 variables for the dynamic model over 20 stages. Its states
are fixed by the inputs (``x = T u + t`` from the stages' ``A_k``, ``B_k``), and each slack
by how far its row is violated; eliminating both leaves the 40 inputs, a dense Hessian
that is cheap to factor, and soft rows that DAQP prices itself, linearly and squared (its
``soft_weights``) as the sparse form priced its slacks. Warm-started from the last plan's
active set, a plan takes a few active-set iterations: in a filter's lap the condensed QP
takes about 0.1 ms (DAQP's solve about half of it) where PIQP took 0.38 ms on the sparse
form; on recorded filter plans first inputs within 3e-5 and slacks within 1e-8 of its.
"""

from __future__ import annotations

from dataclasses import dataclass

import daqp
import numpy as np
from numba import njit

from saferace.numba_cache import announce_compiling
from saferace.safety.stage_qp import StageQP

#: DAQP's infinity: bounds beyond it are none.
DAQP_INFINITY = 1e30
#: DAQP's ``sense`` flag of a soft row (violated at a price).
_SOFT = 8
#: DAQP's exit flags of a solution: optimal, and optimal with soft rows violated.
_SOLVED = (1, 2)


@dataclass(frozen=True)
class SoftPrices:
    """Each soft row's linear and squared price per unit of violation (the sparse form's
    slack costs ``linear eps + squared eps^2``): the lane's, and the speed caps' and the
    terminal heading's."""

    lane: tuple[float, float]
    other: tuple[float, float]


class CondensedPlanQP:
    """A :class:`~saferace.safety.stage_qp.StageQP` with speed caps and a terminal heading
    bound, over its inputs alone: ``1/2 x^T Q x - (Q x_ref)^T x + 1/2 u^T R u + q_u^T u``
    with ``x = T u + t``, ``Q`` diagonal per state (``state_hessian``, the same each
    stage), ``R`` the caller's (:meth:`solve`), plus the soft rows' prices. The speed is
    state ``speed_index``; the terminal heading's rows bound
    ``|e_psi_N| - heading_speed_gain v_N``.

    Rows after the inputs' bounds (DAQP's simple bounds): the steering's change per stage
    (hard), the lane per stage (soft), the speed cap per stage (soft), the speed at least
    zero per stage (hard: the models drive forward only) and the terminal heading, one row
    per sign (soft)."""

    def __init__(
        self,
        horizon: int,
        n_control: int,
        state_hessian: np.ndarray,
        speed_index: int,
        heading_speed_gain: float,
        prices: SoftPrices,
    ) -> None:
        announce_compiling("the predictive filter's plan", condensed_problem)
        N, m = horizon, n_control
        self.state_hessian = np.asarray(state_hessian, dtype=float)
        self.speed_index, self.heading_speed_gain = speed_index, heading_speed_gain
        rows = N * m + 4 * N + 2
        self._soft = np.zeros(rows, dtype=bool)
        linear, squared = np.zeros(rows), np.ones(rows)
        lane = slice(N * m + N, N * m + 2 * N)
        caps, heading = slice(N * m + 2 * N, N * m + 3 * N), slice(rows - 2, rows)
        linear[lane], squared[lane] = prices.lane
        for others in (caps, heading):
            linear[others], squared[others] = prices.other
        for soft in (lane, caps, heading):
            self._soft[soft] = True
        self._lane, self._lane_squared_price = lane, prices.lane[1]
        self._linear_price = linear
        self._inverse_price = 1.0 / (2.0 * squared)  # DAQP's rho: violation^2 / (2 rho)
        self._cold = np.where(self._soft, _SOFT, 0).astype(np.int32)
        self._model: daqp.Model | None = None

    def reset(self) -> None:
        """Forget the last active set (a new episode's first plan starts cold)."""
        self._model = None

    def solve(
        self, qp: StageQP, input_hessian: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The plan's states ``x_1 .. x_N`` ``(N, n)``, inputs ``(N, m)`` and slacks (each
        soft row's violation: the lane's and the speed caps' per stage, then the terminal
        heading's), or None where DAQP found none; ``input_hessian`` is ``R``
        ``(N m, N m)``, and ``q_u`` the first input's linear cost (``qp``'s)."""
        if qp.speed_caps is None or qp.heading_bound is None:
            raise ValueError("the condensed plan needs speed caps and a terminal heading bound")
        N, n, m = qp.B.shape
        gain, offset, hessian, linear, rows, upper, lower, crossed = condensed_problem(
            qp.A,
            qp.B,
            qp.dynamics_offsets,
            self.state_hessian,
            qp.reference,
            input_hessian,
            qp.first_input_linear,
            qp.input_lower,
            qp.input_upper,
            qp.rate_lower,
            qp.rate_upper,
            qp.lane_lower,
            qp.lane_upper,
            qp.speed_caps,
            qp.heading_bound,
            self.speed_index,
            self.heading_speed_gain,
        )
        # A lane tightened past itself is the sparse form's slack of half the gap at its
        # middle, growing as the plan leaves the middle: priced so here (and added back).
        linear_price = self._linear_price.copy()
        linear_price[self._lane] += self._lane_squared_price * crossed
        inputs = self._daqp(hessian, linear, rows, upper, lower, linear_price)
        if inputs is None:
            return None
        values = rows @ inputs
        violation = np.maximum(0.0, np.maximum(values - upper[N * m :], lower[N * m :] - values))
        violation[N : 2 * N] += 0.5 * crossed
        slacks = np.concatenate([violation[N : 3 * N], [violation[-2:].max()]])
        return (gain @ inputs + offset).reshape(N, n), inputs.reshape(N, m), slacks

    def _daqp(
        self,
        hessian: np.ndarray,
        linear: np.ndarray,
        rows: np.ndarray,
        upper: np.ndarray,
        lower: np.ndarray,
        linear_price: np.ndarray,
    ) -> np.ndarray | None:
        """DAQP's minimiser, with the soft rows' linear prices ``linear_price``: the last
        solve's workspace updated in place, which starts from its active set, and where
        that fails a new one started cold."""
        model = self._model
        if model is not None and model.update(hessian, linear, rows, upper, lower) >= 0:
            solution = self._solved(model, linear_price)
            if solution is not None:
                return solution
        self._model = daqp.Model()
        exitflag, _ = self._model.setup(hessian, linear, rows, upper, lower, self._cold)
        if exitflag < 0:
            self._model = None
            return None
        return self._solved(self._model, linear_price)

    def _solved(self, model: daqp.Model, linear_price: np.ndarray) -> np.ndarray | None:
        """``model``'s minimiser with these soft prices, or None where DAQP found none."""
        model.soft_weights(
            rho_l=self._inverse_price, rho_u=self._inverse_price, w_l=linear_price, w_u=linear_price
        )
        x, _, exitflag, _ = model.solve()
        return np.asarray(x) if exitflag in _SOLVED else None


@njit(cache=True)
def condensed_problem(
    A: np.ndarray,
    B: np.ndarray,
    offsets: np.ndarray,
    state_hessian: np.ndarray,
    reference: np.ndarray,
    input_hessian: np.ndarray,
    first_input_linear: np.ndarray,
    input_lower: np.ndarray,
    input_upper: np.ndarray,
    rate_lower: np.ndarray,
    rate_upper: np.ndarray,
    lane_lower: np.ndarray,
    lane_upper: np.ndarray,
    speed_caps: np.ndarray,
    heading_bound: float,
    speed_index: int,
    heading_speed_gain: float,
) -> tuple[np.ndarray, ...]:
    """The condensed QP of :class:`CondensedPlanQP`: ``x = gain u + offset`` (``A``: each
    stage's ``A_k``, the first unused; ``offsets``: the ``c_k``, the first with
    ``A_0 x_0``), the Hessian and linear cost over ``u``, and the rows with their upper and
    lower bounds (the inputs' simple bounds first, DAQP's convention)."""
    N, n, m = B.shape
    gain = np.zeros((N * n, N * m))
    offset = np.empty(N * n)
    for i in range(n):
        offset[i] = offsets[0, i]
        for j in range(m):
            gain[i, j] = B[0, i, j]
    for k in range(1, N):
        row, previous = k * n, (k - 1) * n
        for i in range(n):
            total = offsets[k, i]
            for j in range(n):
                total += A[k, i, j] * offset[previous + j]
            offset[row + i] = total
            for col in range(k * m):
                total = 0.0
                for j in range(n):
                    total += A[k, i, j] * gain[previous + j, col]
                gain[row + i, col] = total
            for j in range(m):
                gain[row + i, k * m + j] = B[k, i, j]
    weighted = np.empty((N * n, N * m))
    error = np.empty(N * n)  # Q (offset - reference)
    for r in range(N * n):
        weight = state_hessian[r % n]
        error[r] = weight * (offset[r] - reference[r // n, r % n])
        for col in range(N * m):
            weighted[r, col] = weight * gain[r, col]
    hessian = input_hessian + gain.T @ weighted
    linear = gain.T @ error
    linear[:m] += first_input_linear

    rows = np.zeros((4 * N + 2, N * m))
    crossed = np.empty(N)
    upper = np.empty(N * m + 4 * N + 2)
    lower = np.empty(N * m + 4 * N + 2)
    upper[: N * m], lower[: N * m] = input_upper.ravel(), input_lower.ravel()
    bounds = N * m  # the rows' bounds start after the simple bounds
    for k in range(N):
        rows[k, k * m] = 1.0
        if k > 0:
            rows[k, (k - 1) * m] = -1.0
        upper[bounds + k], lower[bounds + k] = rate_upper[k], rate_lower[k]
        e_y, speed = k * n, k * n + speed_index
        rows[N + k] = gain[e_y]
        crossed[k] = max(0.0, lane_lower[k] - lane_upper[k])  # tightened past each other
        middle = 0.5 * (lane_lower[k] + lane_upper[k])
        upper[bounds + N + k] = max(lane_upper[k], middle) - offset[e_y]
        lower[bounds + N + k] = min(lane_lower[k], middle) - offset[e_y]
        rows[2 * N + k] = rows[3 * N + k] = gain[speed]
        upper[bounds + 2 * N + k] = speed_caps[k] - offset[speed]
        lower[bounds + 2 * N + k] = -np.inf
        upper[bounds + 3 * N + k] = np.inf
        lower[bounds + 3 * N + k] = -offset[speed]
    last = (N - 1) * n
    for sign, row in ((1.0, 4 * N), (-1.0, 4 * N + 1)):  # +-e_psi_N - gain v_N <= bound
        rows[row] = sign * gain[last + 1] - heading_speed_gain * gain[last + speed_index]
        value = sign * offset[last + 1] - heading_speed_gain * offset[last + speed_index]
        upper[bounds + row], lower[bounds + row] = heading_bound - value, -np.inf
    np.clip(upper, -DAQP_INFINITY, DAQP_INFINITY, upper)
    np.clip(lower, -DAQP_INFINITY, DAQP_INFINITY, lower)
    return gain, offset, hessian, linear, rows, upper, lower, crossed
