"""Barriers that keep the car clear of other cars, in the same HOCBF form as the lane's.

For an opponent at arc length ``s_o`` and lateral offset ``e_y_o``, predicted to go on
along its current line (``e_y_o`` held) from its speed along the track ``v_o``, the
barrier is a superellipse of power ``p = POWER`` in the Frenet frame around it. An
opponent moving ahead of the ego in its line (less than ``B`` to the side) is predicted to
brake as hard as a car can (``OPPONENT_ACCEL_MPS2``, so that a car braking hard ahead is
braked for in time); any other, to hold its speed (one beside can be passed; one behind is
at fault if it runs into the ego):

    h = (ds / A)^p + ((e_y - e_y_o) / B)^p - 1,    ds = s - s_o,  d(ds)/dt = s_dot - v_o

``A`` and ``B`` are the semi-axes: ``2^(1/p)`` times the half extents of the two cars'
bumpers side by side (so that the curve holds the rectangle where the bumpers would
touch), plus a margin. The condition is derived as the lane's are
(:func:`saferace.safety.cbf.barriers.time_derivative`, linear class-K functions with the gains
``CAR_GAINS``), to the order at which the steering appears, and linearised in the
steering around the nominal control. Its rows go into the filter's QP scaled by
``CAR_ROW_WEIGHT``: a squared slack on them costs that factor squared more than on a lane
row, so that where lane and car conditions cannot both hold the car is the one kept clear,
mostly by braking.

A second-order barrier only holds from states where its first-order condition holds too,
and closing on a car at speed from a few metres leaves that set (more so at power 4): on
such states the superellipse's condition let a car accelerate into a car stopped ahead.
So each opponent also has a first-order following barrier, the responsibility-sensitive
safe distance of Shalev-Shwartz et al. (2017) along the track, while the ego is behind it
and near its line (``FOLLOW_WIDTH_M``):

    h_follow = gap - (v^2 / b_ego - v_o^2 / b_o) / 2,    gap = -ds - FOLLOW_GAP_M

(``v`` the ego's speed along the track, ``b_ego = EGO_BRAKE_MPS2`` and ``b_o =
OPPONENT_ACCEL_MPS2``); with the opponent braking as hard as it can,
``dh/dt + lam h >= 0`` is ``a <= b_ego (lam h / v - 1)``: exact, linear in the
acceleration, and braking as hard as the ego may where ``h = 0``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from functools import cache
from typing import Any

import numpy as np
import sympy as sp

from saferace.names import RC10_BUMPER_HALF_EXTENTS_M
from saferace.safety.cbf.barriers import MAX_ORDER, class_k_gains, time_derivative
from saferace.safety.cbf.qp import FilterProblem
from saferace.safety.models import symbolic_model
from saferace.track.frenet import wrap_arc

BUMPER_HALF_LENGTH_M, BUMPER_HALF_WIDTH_M = RC10_BUMPER_HALF_EXTENTS_M
#: Added to each semi-axis of the ellipse (m).
CAR_MARGIN_M = 0.05
#: The power of the superellipse: 2 is an ellipse; 4 hugs the two bumpers' rectangle closer
#: (its lateral semi-axis 0.42 m against the ellipse's 0.49 m).
POWER = 4
#: Its semi-axes along the track and across it (m): the rectangle's corners on the curve.
SEMI_AXIS_S_M = 2.0 ** (1.0 / POWER) * 2.0 * BUMPER_HALF_LENGTH_M + CAR_MARGIN_M
SEMI_AXIS_Y_M = 2.0 ** (1.0 / POWER) * 2.0 * BUMPER_HALF_WIDTH_M + CAR_MARGIN_M
#: How hard an opponent ahead in the ego's line is assumed to brake (m/s^2): as hard as the
#: car can.
OPPONENT_ACCEL_MPS2 = 4.0
#: The following barrier's gap between centres at a standstill (m): a bumper's length plus
#: a margin; the braking it counts on from the ego (m/s^2, a margin below the 4 it has);
#: its class-K gain (1/s).
FOLLOW_GAP_M = 2.0 * BUMPER_HALF_LENGTH_M + 0.1
EGO_BRAKE_MPS2 = 3.5
FOLLOW_GAIN = 2.5
#: The following barrier holds while the ego is less than this to either side of the
#: opponent's line (m): the superellipse's half width and a margin, so that it already holds
#: when a car cuts into the line close behind.
FOLLOW_WIDTH_M = SEMI_AXIS_Y_M + 0.2
#: Rows and barrier values per opponent: the superellipse's, then the following one's.
ROWS_PER_CAR = 2
#: The bound of a row that does not bind (m/s^2): beyond any acceleration the car has.
UNBOUNDED_ACCEL_MPS2 = 100.0
#: The car barrier's class-K gains (1/s), whatever the lane barriers' are.
CAR_GAINS = class_k_gains(2.5)
#: How much heavier a car row's slack weighs than a lane row's (its row is scaled by it).
CAR_ROW_WEIGHT = 10.0

_DS, _E_Y_O, _V_O, _A_O = sp.symbols("ds e_y_o v_o a_o", real=True)
_AXIS_S, _AXIS_Y = sp.symbols("axis_s axis_y", positive=True)
_LAMS = sp.symbols(f"car_lam_1:{MAX_ORDER + 1}", real=True)


@cache
def car_condition(model_name: str) -> tuple[sp.Expr, ...]:
    """``psi_0 .. psi_m`` of the car barrier for ``model_name``."""
    model = symbolic_model(model_name)
    e_y = model.state[0]
    steer = model.control[0]
    state = (*model.state, _DS, _V_O)
    rates = model.x_dot.col_join(sp.Matrix([model.s_dot - _V_O, _A_O]))
    psi = [(_DS / _AXIS_S) ** POWER + ((e_y - _E_Y_O) / _AXIS_Y) ** POWER - 1]
    for lam in _LAMS:
        derivative = time_derivative(psi[-1], state, rates)
        psi.append(derivative + lam * psi[-1])
        if derivative.has(steer):
            return tuple(psi)
    raise ValueError(f"steering never reaches the car barrier of model {model_name}")


@cache
def _car_function(model_name: str) -> Callable[..., list[float]]:
    """``psi_m``, ``d psi_m / du`` and ``h`` of the car barrier, in pure Python."""
    model = symbolic_model(model_name)
    psi = car_condition(model_name)
    args = (
        *model.state, *model.control, model.kappa, *model.params,
        _DS, _E_Y_O, _V_O, _A_O, _AXIS_S, _AXIS_Y, *_LAMS,
    )  # fmt: skip
    final = psi[-1]
    outputs = [final, *(sp.diff(final, c) for c in model.control), psi[0]]
    return sp.lambdify(args, outputs, "math", cse=True)


def along_track_mps(speed_mps: float, e_psi_rad: float, kappa_radpm: float, e_y_m: float) -> float:
    """A car's speed along the centre line, ``v cos(e_psi) / (1 - kappa e_y)`` (the
    Frenet stretch kept above 0.1 off a tight bend's inside)."""
    return speed_mps * math.cos(e_psi_rad) / max(1.0 - kappa_radpm * e_y_m, 0.1)


def opponent_predictions(
    opponents: Sequence[dict[str, Any]],
    track,
    ego_s_m: float,
    noise_m: float = 0.0,
    rng: np.random.Generator | None = None,
) -> list[tuple[float, float, float]]:
    """Each opponent's ``(ds, e_y_o, v_o)`` from its info: the ego's arc length less its
    (within half a lap), its offset, and its speed along the centre line; with ``noise_m``
    the first two get Gaussian noise of that deviation (a perceived opponent)."""
    length = track.length_m
    predictions = []
    for opponent in opponents:
        s_o, e_y_o, e_psi_o = opponent["s_m"], opponent["e_y_m"], opponent["e_psi_rad"]
        kappa = track.centerline.curvature_scalar(s_o)
        v_o = along_track_mps(opponent["speed_mps"], e_psi_o, kappa, e_y_o)
        ds = wrap_arc(ego_s_m - s_o, length)
        if noise_m > 0.0:
            noise = (rng or np.random.default_rng()).normal(0.0, noise_m, 2)
            ds, e_y_o = ds + noise[0], e_y_o + noise[1]
        predictions.append((ds, e_y_o, v_o))
    return predictions


def car_rows(
    model_name: str,
    params: tuple[float, ...],
    state: np.ndarray,
    kappa_radpm: float,
    u0: np.ndarray,
    predictions: Sequence[tuple[float, float, float]],
    gains: tuple[float, ...],
    widening_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``a u <= b`` rows (scaled by ``CAR_ROW_WEIGHT``) and ``h`` of each opponent's car
    barrier at the ego's model ``state``; ``widening_m`` grows both semi-axes (an opponent
    state known with noise)."""
    function = _car_function(model_name)
    steer0, accel0 = float(u0[0]), float(u0[1])
    axes = (SEMI_AXIS_S_M + widening_m, SEMI_AXIS_Y_M + widening_m)
    ego = (*state, steer0, accel0, kappa_radpm, *params)
    rows = []
    for ds, e_y_o, v_o in predictions:
        braking_ahead = ds < 0.0 and v_o > 0.0 and abs(float(state[0]) - e_y_o) < SEMI_AXIS_Y_M
        worst_accel = -OPPONENT_ACCEL_MPS2 if braking_ahead else 0.0
        rows.append(function(*ego, ds, e_y_o, v_o, worst_accel, *axes, *gains))
    values = np.array(rows).reshape(len(predictions), 4)
    psi, gradient, h = values[:, 0], values[:, 1:3], values[:, 3]
    b = psi - gradient @ np.array([steer0, accel0])
    speed = float(state[symbolic_model(model_name).speed_index])
    along = along_track_mps(speed, float(state[1]), kappa_radpm, float(state[0]))
    follow = [
        _follow_row(ds, float(state[0]) - e_y_o, v_o, along) for ds, e_y_o, v_o in predictions
    ]
    a_rows = np.empty((ROWS_PER_CAR * len(predictions), 2))
    a_rows[0::2], a_rows[1::2] = -gradient, [[0.0, 1.0]] * len(predictions)
    b_rows = np.empty(ROWS_PER_CAR * len(predictions))
    b_rows[0::2], b_rows[1::2] = b, [row[0] for row in follow]
    h_rows = np.empty(ROWS_PER_CAR * len(predictions))
    h_rows[0::2], h_rows[1::2] = h, [row[1] for row in follow]
    return CAR_ROW_WEIGHT * a_rows, CAR_ROW_WEIGHT * b_rows, h_rows


def _follow_row(ds: float, dy: float, v_o: float, along_mps: float) -> tuple[float, float]:
    """``(bound on the acceleration, h_follow)`` of the following barrier; no bound (a large
    one) unless the opponent is ahead in the ego's line."""
    gap = -ds - FOLLOW_GAP_M
    speed, v_o = max(along_mps, 0.0), max(v_o, 0.0)
    h = gap - 0.5 * (speed * speed / EGO_BRAKE_MPS2 - v_o * v_o / OPPONENT_ACCEL_MPS2)
    if ds >= 0.0 or abs(dy) >= FOLLOW_WIDTH_M:
        return UNBOUNDED_ACCEL_MPS2, h
    bound = EGO_BRAKE_MPS2 * (FOLLOW_GAIN * h / max(speed, 0.1) - 1.0)
    return min(bound, UNBOUNDED_ACCEL_MPS2), h


def follow_bound_mps2(
    predictions: Sequence[tuple[float, float, float]], e_y_m: float, along_mps: float
) -> float:
    """The tightest bound the opponents' following barriers put on the acceleration of an
    ego at offset ``e_y_m`` going ``along_mps`` along the track (the predictive filter's
    car rule: its plan has no cars)."""
    bounds = (_follow_row(ds, e_y_m - e_y_o, v_o, along_mps)[0] for ds, e_y_o, v_o in predictions)
    return min(bounds, default=UNBOUNDED_ACCEL_MPS2)


def car_conflict(
    problem: FilterProblem, solution, car_rows: int, lane_rows: int, infeasible_slack: float
) -> bool:
    """Whether the solution cannot keep clear of a car (a car row needs slack) or keeps
    clear of one at the lane's cost (a lane row needs slack while a car row binds): then the
    filter brakes in its lane instead."""
    car = slice(len(problem.b) - car_rows, None)
    if solution.slack[car].max() > infeasible_slack:  # on rows scaled by CAR_ROW_WEIGHT
        return True
    margins = problem.b[car] - problem.a[car] @ solution.u
    binding = margins.min() < CAR_ROW_WEIGHT * infeasible_slack
    return bool(binding and solution.slack[:lane_rows].max() > infeasible_slack)


def follow_capped(
    problem: FilterProblem, car_rows: int, accel_mps2: float, box: tuple[np.ndarray, np.ndarray]
) -> float:
    """``accel_mps2`` within the tightest bound the following rows of ``problem`` put on the
    acceleration, and within the action ``box``: the filter's fallbacks leave the QP, not
    the car ahead."""
    follow = problem.b[len(problem.b) - car_rows + 1 :: ROWS_PER_CAR] / CAR_ROW_WEIGHT
    return float(max(min(accel_mps2, follow.min()), box[0][1]))


def with_car_rows(
    problem: FilterProblem, h: np.ndarray, rows: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> tuple[FilterProblem, np.ndarray]:
    """The filter's ``problem`` and its barrier values ``h`` (a row per state sample) with
    the opponents' ``rows`` (:func:`car_rows`: no sample spread on them) and their ``h``."""
    a, b, car_h = rows
    covariance = problem.covariance
    if covariance is not None:
        covariance = np.concatenate([covariance, np.zeros((len(b), 3, 3))])
    problem = dataclasses.replace(
        problem, a=np.vstack([problem.a, a]), b=np.append(problem.b, b), covariance=covariance
    )
    return problem, np.column_stack([h, np.broadcast_to(car_h, (len(h), len(b)))])


def names(opponents: Sequence[str]) -> tuple[str, ...]:
    """The filter's constraint names of the opponents' rows, in their order."""
    return tuple(name for car in opponents for name in (car, f"{car}_follow"))
