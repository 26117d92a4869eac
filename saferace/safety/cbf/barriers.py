"""Lane and heading barriers and their higher-order CBF conditions, derived from a model.

Barriers (``h >= 0`` is safe; widths are the track's real half widths at ``s``):

- ``lane_left  = w_left  - e_y - half_width``
- ``lane_right = w_right + e_y - half_width``
- ``heading_left  = theta_max - e_psi``
- ``heading_right = theta_max + e_psi``

For each, code finds the order ``m`` at which the steering first appears in a time
derivative (the relative degree in steering: 2 for the lane with the kinematic and the
full dynamic model, 3 with the paper's simplified model, 1 or 2 for the heading) and
builds the HOCBF condition of Xiao & Belta: ``psi_0 = h``,
``psi_i = d/dt psi_{i-1} + alpha_i(psi_{i-1})``, and requires ``psi_m >= 0``. The class-K
functions are linear, ``alpha_i(x) = lam_i x``, except that the lane barriers' first one
saturates to the stopping condition of a lateral deceleration ``a`` when one is given:
``alpha_1(h) = lam_1 h / (1 + lam_1^4 h^2 / (4 a^2))^(1/4)`` (smooth, increasing) is
``lam_1 h`` near the edge and ``sqrt(2 a h)`` far from it, so ``psi_1 >= 0`` never lets
the car head for the edge faster than it can turn away at ``a``. With ``a = inf`` and one
``lam`` for every order this is the paper's condition,
``sum_k binom(m, k) lam^(m-k) h^(k) >= 0``. The half widths change along the track at their
local slopes (``dw/dt = dw/ds * s_dot``, the slope held constant); ``theta_max`` and the
curvature are held constant (the curvature's rate along ``s`` is neglected). Without the
slopes, a lane narrowing at 0.03 m/m holds a filtered car about ``2 * 0.03 * v / lam``
beyond its barrier.

``psi_m`` is affine in the acceleration; in the steering it is affine for the dynamic
models and goes through ``tan`` for the kinematic one. Either way the filter uses its
linearisation around the nominal control ``u_0``:
``psi_m(x, u) ~ psi_m(x, u_0) + d psi_m / du (u - u_0) >= 0``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import cache

import numpy as np
import sympy as sp

from saferace.safety.models import symbolic_model

BARRIER_NAMES = ("lane_left", "lane_right", "heading_left", "heading_right")
MAX_ORDER = 4

_W_LEFT, _W_RIGHT, _HALF_WIDTH, _THETA_MAX = sp.symbols(
    "w_left w_right half_width theta_max", real=True
)
#: The class-K gain of each order, ``lam_1 .. lam_MAX_ORDER``.
_LAMS = sp.symbols(f"lam_1:{MAX_ORDER + 1}", real=True)
#: The lateral deceleration the lane barriers' first class-K function saturates to.
_LATERAL_DECEL = sp.Symbol("lateral_decel", positive=True)
#: How fast each half width changes along the track (m per m of centerline).
_W_LEFT_SLOPE, _W_RIGHT_SLOPE = sp.symbols("w_left_slope w_right_slope", real=True)


def barrier_expression(name: str, e_y: sp.Symbol, e_psi: sp.Symbol) -> sp.Expr:
    """``h`` of a named barrier in the model's symbols."""
    return {
        "lane_left": _W_LEFT - e_y - _HALF_WIDTH,
        "lane_right": _W_RIGHT + e_y - _HALF_WIDTH,
        "heading_left": _THETA_MAX - e_psi,
        "heading_right": _THETA_MAX + e_psi,
    }[name]


@dataclass(frozen=True)
class HOCBFCondition:
    """``psi_m(x, u) >= 0`` of one barrier: its order and the chain ``psi_0 .. psi_m``."""

    barrier: str
    order: int
    psi: tuple[sp.Expr, ...]


def time_derivative(expr: sp.Expr, state: tuple[sp.Symbol, ...], x_dot: sp.Matrix) -> sp.Expr:
    """``d expr / dt = grad(expr) . x_dot`` along the model."""
    return sum(sp.diff(expr, x) * x_dot[i] for i, x in enumerate(state))


def _with_lane_widths(model) -> tuple[tuple[sp.Symbol, ...], sp.Matrix]:
    """The model's state and rates extended by the half widths, which change with ``s``."""
    state = (*model.state, _W_LEFT, _W_RIGHT)
    rates = model.x_dot.col_join(
        sp.Matrix([_W_LEFT_SLOPE * model.s_dot, _W_RIGHT_SLOPE * model.s_dot])
    )
    return state, rates


def class_k(barrier: str, order: int, lam: sp.Symbol, x: sp.Expr) -> sp.Expr:
    """``alpha_order(x)`` of ``barrier`` (see the module docstring)."""
    if order == 1 and barrier.startswith("lane"):
        return lam * x / (1 + lam**4 * x**2 / (4 * _LATERAL_DECEL**2)) ** sp.Rational(1, 4)
    return lam * x


@cache
def hocbf_condition(model_name: str, barrier: str) -> HOCBFCondition:
    """Derive the HOCBF condition of ``barrier`` for ``model_name`` (cached per process)."""
    model = symbolic_model(model_name)
    e_y, e_psi = model.state[0], model.state[1]
    steer = model.control[0]
    psi = [barrier_expression(barrier, e_y, e_psi)]
    state, rates = _with_lane_widths(model)
    for lam in _LAMS:
        derivative = time_derivative(psi[-1], state, rates)
        psi.append(derivative + class_k(barrier, len(psi), lam, psi[-1]))
        if derivative.has(steer):
            break
    else:
        raise ValueError(f"steering never reaches barrier {barrier} of model {model_name}")
    return HOCBFCondition(barrier=barrier, order=len(psi) - 1, psi=tuple(psi))


@cache
def _constraint_function(model_name: str) -> Callable[..., list[float]]:
    """One pure-Python function giving, per barrier, ``psi_m``, ``d psi_m / du`` and ``h``."""
    model = symbolic_model(model_name)
    args = (
        *model.state,
        *model.control,
        model.kappa,
        *model.params,
        _W_LEFT,
        _W_RIGHT,
        _HALF_WIDTH,
        _THETA_MAX,
        *_LAMS,
        _LATERAL_DECEL,
        _W_LEFT_SLOPE,
        _W_RIGHT_SLOPE,
    )
    outputs = []
    for name in BARRIER_NAMES:
        condition = hocbf_condition(model_name, name)
        final = condition.psi[-1]
        outputs += [final, *(sp.diff(final, c) for c in model.control), condition.psi[0]]
    return sp.lambdify(args, outputs, "math", cse=True)


def class_k_gains(lam: float | tuple[float, ...]) -> tuple[float, ...]:
    """The gain of each HOCBF order from one ``lam`` or a tuple ``(lam_1, lam_2, ...)``."""
    gains = tuple(float(g) for g in lam) if isinstance(lam, Iterable) else (float(lam),)
    if not gains or len(gains) > MAX_ORDER or min(gains) <= 0.0:
        raise ValueError(f"need 1 to {MAX_ORDER} positive class-K gains, got {lam!r}")
    return gains + gains[-1:] * (MAX_ORDER - len(gains))


def relative_degrees(model_name: str) -> dict[str, int]:
    """Order of each barrier's HOCBF condition for a model."""
    return {name: hocbf_condition(model_name, name).order for name in BARRIER_NAMES}


@dataclass(frozen=True)
class BarrierContext:
    """What the barriers need besides the state: lane half widths, car size, limits."""

    w_left_m: float
    w_right_m: float
    half_width_m: float
    theta_max_rad: float
    lam: float | tuple[float, ...]
    lateral_decel_mps2: float = math.inf  # inf: linear class-K functions, as in the paper
    w_left_slope: float = 0.0  # d w_left / ds
    w_right_slope: float = 0.0

    @property
    def gains(self) -> tuple[float, ...]:
        """``lam_1 .. lam_MAX_ORDER``: one ``lam`` for every order, or ``lam`` per order with
        the last one repeated for higher orders."""
        return class_k_gains(self.lam)


def linearised_constraints(
    model_name: str,
    params: tuple[float, ...],
    states: np.ndarray,
    kappa_radpm: float | np.ndarray,
    u0: np.ndarray,
    context: BarrierContext,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``a u <= b`` per state sample and barrier (``a (n, B, 2)``, ``b (n, B)``), and ``h (n, B)``.

    ``states`` is ``(n, n_state)`` (or one state), ``kappa_radpm`` the reference curvature of
    each sample (or one for all). ``psi_m(x, u0) + J (u - u0) >= 0`` becomes
    ``-J u <= psi_m(x, u0) - J u0``.
    """
    states = np.atleast_2d(np.asarray(states, dtype=float))
    n, count = len(states), len(BARRIER_NAMES)
    kappas = np.broadcast_to(np.asarray(kappa_radpm, dtype=float), (n,)).tolist()
    tail = (
        *params,
        context.w_left_m,
        context.w_right_m,
        context.half_width_m,
        context.theta_max_rad,
        *context.gains,
        context.lateral_decel_mps2,
        context.w_left_slope,
        context.w_right_slope,
    )
    steer0, accel0 = float(u0[0]), float(u0[1])
    function = _constraint_function(model_name)
    values = np.array(
        [
            function(*x, steer0, accel0, kappa, *tail)
            for x, kappa in zip(states.tolist(), kappas, strict=True)
        ]
    ).reshape(n, count, 4)
    psi, gradient, h = values[:, :, 0], values[:, :, 1:3], values[:, :, 3]
    b = psi - gradient[:, :, 0] * steer0 - gradient[:, :, 1] * accel0
    return -gradient, b, h
