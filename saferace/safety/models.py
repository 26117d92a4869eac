"""Vehicle models in Frenet coordinates, shared by the expert MPC and the safety filter.

Each model is written once in sympy; code derives its Jacobians (and, in the safety
filter, its Lie derivatives), and ``lambdify`` turns them into fast numeric functions.
The state excludes the arc length ``s``: the dynamics depend on ``s`` only through the
reference curvature ``kappa``, a parameter here; :meth:`FrenetModel.s_dot` gives its rate.

- ``kinematic`` (paper Sec. 3.3, with ``tan`` where the paper writes ``sin``):
  state ``[e_y, e_psi, v, v_y]``. ``v_y`` is the measured lateral velocity of the centre of
  mass, held constant: the body's side slip (about ``l_r / L * steer * v`` even without
  tyre slip), which the paper's ``e_y' = v sin(e_psi)`` leaves out and which otherwise
  drifts a filtered car past its lane barrier at a steady ``2 v_y / lam``.
- ``dynamic``: the linear-tyre single-track model with all coupling terms,
  state ``[e_y, e_psi, v_x, v_y, r]``. Cornering stiffness per axle is
  ``C = C_0 + D v_x`` (see :class:`~saferace.safety.vehicle_params.VehicleParams`).
- ``dynamic-paper``: the paper's simplified dynamic model, which drops the coupling
  of ``v_y`` and ``r`` and the steering input on ``v_y`` (steering then reaches the lateral
  offset only through ``r``, so the lane barrier has relative degree 3).

Controls are ``[steer_rad, accel_mps2]``: the front-wheel angle and the longitudinal
acceleration. ``s_dot = (v_x cos e_psi - v_y sin e_psi) / (1 - kappa e_y)`` is exact.
Speeds below ``MIN_SPEED_MPS`` are raised to it where a model divides by speed.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache

import numpy as np
import sympy as sp
from numba import njit

from saferace.numba_cache import recompiled_when_changed
from saferace.safety.matrix_exponential import expm_batch, expm_stacked
from saferace.safety.model_code import stage_linearisation
from saferace.safety.vehicle_params import VehicleParams

MIN_SPEED_MPS = 0.5
MAX_RK4_STEP_S = 0.01
CONTROL_NAMES = ("steer_rad", "accel_mps2")
PARAM_NAMES = (
    "mass_kg",
    "yaw_inertia_kgm2",
    "lf_m",
    "lr_m",
    "cf0_npr",
    "df_nspmr",
    "cr0_npr",
    "dr_nspmr",
)


def param_values(params: VehicleParams) -> tuple[float, ...]:
    """``params`` in the order of ``PARAM_NAMES``: how the lambdified models take them."""
    return tuple(float(getattr(params, name)) for name in PARAM_NAMES)


@dataclass(frozen=True)
class SymbolicModel:
    """A model's sympy form: state, control, curvature and parameter symbols and ``x_dot``."""

    name: str
    state: tuple[sp.Symbol, ...]
    control: tuple[sp.Symbol, ...]
    kappa: sp.Symbol
    params: tuple[sp.Symbol, ...]
    x_dot: sp.Matrix
    s_dot: sp.Expr
    speed_index: int


def _symbols() -> dict[str, sp.Symbol]:
    names = "e_y e_psi v v_x v_y r steer accel kappa m I_z l_f l_r C_f0 D_f C_r0 D_r"
    return dict(zip(names.split(), sp.symbols(names, real=True), strict=True))


def _kinematic() -> SymbolicModel:
    S = _symbols()
    e_y, e_psi, v, v_y, delta, a, kappa = (
        S["e_y"],
        S["e_psi"],
        S["v"],
        S["v_y"],
        S["steer"],
        S["accel"],
        S["kappa"],
    )
    params = tuple(S[k] for k in ("m", "I_z", "l_f", "l_r", "C_f0", "D_f", "C_r0", "D_r"))
    s_dot = (v * sp.cos(e_psi) - v_y * sp.sin(e_psi)) / (1 - kappa * e_y)
    x_dot = sp.Matrix(
        [
            v * sp.sin(e_psi) + v_y * sp.cos(e_psi),
            v * sp.tan(delta) / (S["l_f"] + S["l_r"]) - kappa * s_dot,
            a,
            0,
        ]
    )
    return SymbolicModel(
        "kinematic", (e_y, e_psi, v, v_y), (delta, a), kappa, params, x_dot, s_dot, 2
    )


def _dynamic(paper: bool) -> SymbolicModel:
    S = _symbols()
    e_y, e_psi, v_x, v_y, r = S["e_y"], S["e_psi"], S["v_x"], S["v_y"], S["r"]
    delta, a, kappa = S["steer"], S["accel"], S["kappa"]
    m, I_z, l_f, l_r = (S[k] for k in ("m", "I_z", "l_f", "l_r"))
    C_f = S["C_f0"] + S["D_f"] * v_x  # cornering stiffness per axle, growing with speed
    C_r = S["C_r0"] + S["D_r"] * v_x
    s_dot = (v_x * sp.cos(e_psi) - v_y * sp.sin(e_psi)) / (1 - kappa * e_y)
    if paper:
        v_y_dot = -(C_f + C_r) / (m * v_x) * v_y
        r_dot = -(l_f**2 * C_f + l_r**2 * C_r) / (I_z * v_x) * r + l_f * C_f / I_z * delta
        v_x_dot = a
    else:
        v_y_dot = (
            -(C_f + C_r) / (m * v_x) * v_y
            + ((l_r * C_r - l_f * C_f) / (m * v_x) - v_x) * r
            + C_f / m * delta
        )
        r_dot = (
            (l_r * C_r - l_f * C_f) / (I_z * v_x) * v_y
            - (l_f**2 * C_f + l_r**2 * C_r) / (I_z * v_x) * r
            + l_f * C_f / I_z * delta
        )
        v_x_dot = a + v_y * r
    x_dot = sp.Matrix(
        [
            v_x * sp.sin(e_psi) + v_y * sp.cos(e_psi),
            r - kappa * s_dot,
            v_x_dot,
            v_y_dot,
            r_dot,
        ]
    )
    params = tuple(S[k] for k in ("m", "I_z", "l_f", "l_r", "C_f0", "D_f", "C_r0", "D_r"))
    name = "dynamic-paper" if paper else "dynamic"
    return SymbolicModel(
        name, (e_y, e_psi, v_x, v_y, r), (delta, a), kappa, params, x_dot, s_dot, 2
    )


SYMBOLIC_MODELS: dict[str, Callable[[], SymbolicModel]] = {
    "kinematic": _kinematic,
    "dynamic": lambda: _dynamic(paper=False),
    "dynamic-paper": lambda: _dynamic(paper=True),
}


class FrenetModel:
    """Numeric ``f(x, u, kappa)``, its Jacobians and discretisation, for one parameter set."""

    def __init__(self, name: str, params: VehicleParams) -> None:
        if name not in SYMBOLIC_MODELS:
            raise ValueError(
                f"unknown vehicle model {name!r}: use one of {', '.join(SYMBOLIC_MODELS)}"
            )
        self.name = name
        self.params = params
        self.symbolic = symbolic_model(name)
        self.state_names = tuple(str(x) for x in self.symbolic.state)
        self.n_state = len(self.symbolic.state)
        self.n_control = len(self.symbolic.control)
        self.speed_index = self.symbolic.speed_index
        self._param_values = param_values(params)
        self._f, self._s_dot, self._linearised = _lambdified(name)
        self._param_array = np.array(self._param_values)

    def state_from(
        self, e_y: float, e_psi: float, v_x: float, v_y: float = 0.0, r: float = 0.0
    ) -> np.ndarray:
        """This model's state vector from the full Frenet/body state (``v`` is ``v_x``)."""
        values = {"e_y": e_y, "e_psi": e_psi, "v": v_x, "v_x": v_x, "v_y": v_y, "r": r}
        return np.array([values[name] for name in self.state_names], dtype=float)

    def _args(self, x: np.ndarray, u: np.ndarray, kappa: float) -> tuple[float, ...]:
        values = [float(v) for v in x]
        values[self.speed_index] = max(values[self.speed_index], MIN_SPEED_MPS)
        return (*values, float(u[0]), float(u[1]), float(kappa), *self._param_values)

    def f(self, x: np.ndarray, u: np.ndarray, kappa: float) -> np.ndarray:
        """State derivative."""
        return np.asarray(self._f(*self._args(x, u, kappa)), dtype=float).ravel()

    def jacobians(
        self, x: np.ndarray, u: np.ndarray, kappa: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(df/dx, df/du)`` at ``(x, u)``."""
        _, a, b = self._split(np.array(self._linearised(*self._args(x, u, kappa))))
        return a, b

    def _split(self, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(f, df/dx, df/du)`` of the generated function's flat output (a leading axis
        of stages is kept)."""
        n, m, lead = self.n_state, self.n_control, flat.shape[:-1]
        jac_x = flat[..., n : n + n * n].reshape(*lead, n, n)
        return flat[..., :n], jac_x, flat[..., n + n * n :].reshape(*lead, n, m)

    def s_dot(self, x: np.ndarray, kappa: float) -> float:
        """Rate of the centerline arc length."""
        return float(self._s_dot(*self._args(x, np.zeros(2), kappa)))

    def along_track_speeds_mps(self, xs: np.ndarray) -> np.ndarray:
        """``v_x cos e_psi - v_y sin e_psi`` of each state in ``xs`` (leading axes kept):
        :meth:`s_dot` is this over ``1 - kappa e_y``, so many stages' rates cost one
        vectorised call and a division each."""
        e_psi, v_y = xs[..., 1], xs[..., 3]  # v_y is the fourth state of every model
        v_x = np.maximum(xs[..., self.speed_index], MIN_SPEED_MPS)
        return v_x * np.cos(e_psi) - v_y * np.sin(e_psi)

    def step(self, x: np.ndarray, u: np.ndarray, kappa: float, dt_s: float) -> np.ndarray:
        """Integrate the nonlinear model over ``dt_s`` with ``u`` and ``kappa`` held.

        RK4 in sub-steps of at most ``MAX_RK4_STEP_S``: the identified tyres make the
        lateral dynamics stiff (time constants of about 10 ms).
        """
        count = max(1, math.ceil(dt_s / MAX_RK4_STEP_S - 1e-9))
        h = dt_s / count
        for _ in range(count):
            k1 = self.f(x, u, kappa)
            k2 = self.f(x + 0.5 * h * k1, u, kappa)
            k3 = self.f(x + 0.5 * h * k2, u, kappa)
            k4 = self.f(x + h * k3, u, kappa)
            x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        return x

    def discretize(
        self, x: np.ndarray, u: np.ndarray, kappa: float, dt_s: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(A_d, B_d, c_d)`` with ``x+ ~ A_d x + B_d u + c_d`` near ``(x, u)`` (zero-order hold).

        The model is linearised at ``(x, u)`` and the affine system discretised exactly
        by one matrix exponential.
        """
        a, b = self.jacobians(x, u, kappa)
        n, m = b.shape
        block = np.zeros((n + m + 1, n + m + 1))
        block[:n, :n], block[:n, n:-1], block[:n, -1] = a, b, self.f(x, u, kappa) - a @ x - b @ u
        return _zero_order_hold(block, n, dt_s)

    def discretize_stages_with_steering_lag(
        self,
        xs: np.ndarray,
        us: np.ndarray,
        kappas: np.ndarray,
        dt_s: float,
        steer_time_constant_s: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`discretize` with the steering servo in front of the model, at every stage
        ``k`` of a horizon at once: ``(A_d, B_d, c_d)`` stacked ``(N, n + 1, ...)``.

        The state gains the wheels' angle ``delta`` (last entry of each ``xs[k]``), which
        follows the commanded angle ``u[0]`` as a first-order lag,
        ``delta' = (u[0] - delta) / tau``; the model sees ``[delta, u[1]]``. At racing speed
        the servo's lag (about one control step) is what a controller that ignores it
        turns into a weave. The stages' linearisation is one call of the model's compiled
        code (:mod:`~saferace.safety.model_code`), their matrix exponentials one batched
        call.
        """
        n = self.n_state
        xs, us = np.asarray(xs, dtype=float), np.asarray(us, dtype=float)
        rate = 1.0 / steer_time_constant_s
        states = xs[:, :n].copy()
        states[:, self.speed_index] = np.maximum(states[:, self.speed_index], MIN_SPEED_MPS)
        flat = _stage_linearisation(self.name)(
            states, xs[:, n].copy(), us[:, 1].copy(), np.asarray(kappas, dtype=float),
            self._param_array,
        )  # fmt: skip
        f, a, b = self._split(flat)
        return _lagged_zero_order_hold(
            f, a, b, np.ascontiguousarray(xs), np.ascontiguousarray(us), dt_s, rate
        )


@recompiled_when_changed(expm_stacked)
@njit(cache=True)
def _lagged_zero_order_hold(
    f: np.ndarray,
    jac_x: np.ndarray,
    jac_u: np.ndarray,
    xs: np.ndarray,
    us: np.ndarray,
    dt_s: float,
    rate: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each stage's ``(A_d, B_d, c_d)`` of the model linearised at ``(xs[k], us[k])`` (its
    ``f``, ``df/dx``, ``df/du``) with the servo's lag in front: the state gains the wheels'
    angle (``xs[k, -1]``), ``delta' = rate (u[0] - delta)``, which the model sees as its
    first input; one matrix exponential of ``[[A, B, c], [0, 0, 0]] dt_s`` per stage."""
    stages, n = f.shape
    m = jac_u.shape[2]
    size = n + 1  # the lagged system's state
    width = size + m + 1
    block = np.zeros((width, width, stages))  # stacked along the last axis (expm_stacked)
    for k in range(stages):
        block[:n, :n, k] = jac_x[k]
        block[:n, n, k] = jac_u[k, :, 0]
        block[:n, size + 1 : size + m, k] = jac_u[k, :, 1:]
        block[n, n, k], block[n, size, k] = -rate, rate
        for i in range(size):  # c = x_dot - [A B] [x u] at the stage's point
            total = f[k, i] if i < n else rate * (us[k, 0] - xs[k, n])
            for j in range(size):
                total -= block[i, j, k] * xs[k, j]
            for j in range(m):
                total -= block[i, size + j, k] * us[k, j]
            block[i, -1, k] = total
    exp = expm_stacked(block * dt_s)
    A = np.empty((stages, size, size))
    B = np.empty((stages, size, m))
    c = np.empty((stages, size))
    for k in range(stages):
        A[k], B[k], c[k] = exp[:size, :size, k], exp[:size, size:-1, k], exp[:size, -1, k]
    return A, B, c


def _zero_order_hold(
    block: np.ndarray, n: int, dt_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``x' = a x + b u + c`` with ``u`` held over ``dt_s``, discretised exactly by one
    matrix exponential of ``block = [[a, b, c], [0, 0, 0]]`` (``n`` states): ``(A_d, B_d,
    c_d)``. Leading axes of ``block`` are a batch of systems, exponentiated together."""
    exp = expm_batch(block * dt_s)
    return exp[..., :n, :n], exp[..., :n, n:-1], exp[..., :n, -1]


def lane_model_states(model: SymbolicModel, lane: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """The model's state for each lane-state sample ``(e_y, e_psi, ...)`` and the measured
    velocities ``[v_x, v_y, r]`` (the forward speed at least ``MIN_SPEED_MPS``)."""
    v_x = max(float(velocity[0]), MIN_SPEED_MPS)
    columns: dict[str, np.ndarray | float] = {
        "e_y": lane[:, 0],
        "e_psi": lane[:, 1],
        "v": v_x,
        "v_x": v_x,
        "v_y": float(velocity[1]),
        "r": float(velocity[2]),
    }
    return np.column_stack([np.broadcast_to(columns[str(x)], len(lane)) for x in model.state])


@cache
def symbolic_model(name: str) -> SymbolicModel:
    """The sympy form of a model (built once per process)."""
    return SYMBOLIC_MODELS[name]()


@cache
def _stage_linearisation(name: str) -> Callable:
    """Model ``name``'s ``f`` with both Jacobians at many stages, compiled
    (:func:`~saferace.safety.model_code.stage_linearisation`)."""
    model = symbolic_model(name)
    state, control = sp.Matrix(model.state), sp.Matrix(model.control)
    jac_x, jac_u = model.x_dot.jacobian(state), model.x_dot.jacobian(control)
    outputs = [*model.x_dot, *jac_x, *jac_u]
    return stage_linearisation(name, model.state, model.control, model.kappa, model.params, outputs)


@cache
def _lambdified(name: str) -> tuple[Callable, Callable, Callable]:
    """``f``, ``s_dot``, and ``f`` with both Jacobians in one flat list (numpy code with
    common subexpressions shared: one call linearises all stages of a plan, given arrays)."""
    model = symbolic_model(name)
    args = (*model.state, *model.control, model.kappa, *model.params)
    state, control = sp.Matrix(model.state), sp.Matrix(model.control)
    jac_x, jac_u = model.x_dot.jacobian(state), model.x_dot.jacobian(control)
    # Plain lists lambdify to pure-Python ``math`` code: microseconds per call on floats.
    return (
        sp.lambdify(args, list(model.x_dot), "math"),
        sp.lambdify(args, model.s_dot, "math"),
        sp.lambdify(args, [*model.x_dot, *jac_x, *jac_u], "numpy", cse=True),
    )
