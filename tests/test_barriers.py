"""Lane and heading barriers: orders derived from the models, symmetry, and Lie derivatives."""

from __future__ import annotations

import numpy as np
import pytest
import sympy as sp

from saferace.safety.cbf.barriers import (
    BARRIER_NAMES,
    MAX_ORDER,
    BarrierContext,
    class_k_gains,
    hocbf_condition,
    linearised_constraints,
    relative_degrees,
)
from saferace.safety.models import FrenetModel, param_values, symbolic_model
from saferace.safety.vehicle_params import VehicleParams

PARAMS = VehicleParams(
    cf0_npr=20.0, df_nspmr=150.0, cr0_npr=30.0, dr_nspmr=180.0, yaw_inertia_kgm2=0.08
)
PARAM_VALUES = param_values(PARAMS)
KAPPA_RADPM = 0.3
CONTEXT = BarrierContext(
    w_left_m=0.5,
    w_right_m=0.5,
    half_width_m=0.15,
    theta_max_rad=np.pi / 4,
    lam=(8.0, 2.5),
    lateral_decel_mps2=3.0,
)


def class_k_value(barrier: str, order: int, lam: float, x: float) -> float:
    """The class-K functions written out: the lane's first saturates at sqrt(2 a x)."""
    if order == 1 and barrier.startswith("lane"):
        return lam * x / (1.0 + lam**4 * x**2 / (4.0 * CONTEXT.lateral_decel_mps2**2)) ** 0.25
    return lam * x


def test_gains_per_order_repeat_the_last_and_refuse_bad_values():
    assert class_k_gains(2.5) == (2.5,) * MAX_ORDER
    assert class_k_gains((8.0, 2.5)) == (8.0,) + (2.5,) * (MAX_ORDER - 1)
    for bad in ((), (1.0, 0.0), (1.0,) * (MAX_ORDER + 1)):
        with pytest.raises(ValueError, match="class-K gains"):
            class_k_gains(bad)


def test_lane_condition_lets_the_car_approach_no_faster_than_it_can_turn_away():
    """psi_1 = dh/dt + alpha_1(h): lam_1 h near the edge, sqrt(2 a h) far from it."""
    psi_1 = hocbf_condition("kinematic", "lane_left").psi[1]
    at_rest = {"e_y": 0.0, "e_psi": 0.0, "v_y": 0.0, "half_width": 0.0, "w_left_slope": 0.0}
    at_rest["lam_1"] = 8.0
    for decel, h, expected in (
        (3.0, 1e-4, 8.0 * 1e-4),
        (3.0, 50.0, np.sqrt(2 * 3.0 * 50.0)),
        (np.inf, 50.0, 8.0 * 50.0),  # the paper's linear function
    ):
        values = {**at_rest, "lateral_decel": decel, "w_left": h}
        value = psi_1.subs({symbol: values.get(symbol.name, 1.0) for symbol in psi_1.free_symbols})
        assert float(value) == pytest.approx(expected, rel=0.01)


def test_orders_follow_the_models_relative_degree_in_steering():
    assert relative_degrees("kinematic") == {
        "lane_left": 2,
        "lane_right": 2,
        "heading_left": 1,
        "heading_right": 1,
    }
    assert relative_degrees("dynamic") == {
        "lane_left": 2,
        "lane_right": 2,
        "heading_left": 2,
        "heading_right": 2,
    }
    # The paper's simplified model: steering reaches the lateral offset at the third derivative.
    assert relative_degrees("dynamic-paper") == {
        "lane_left": 3,
        "lane_right": 3,
        "heading_left": 2,
        "heading_right": 2,
    }


@pytest.mark.parametrize("model_name", ["kinematic", "dynamic", "dynamic-paper"])
def test_barriers_are_zero_on_the_boundary_and_symmetric(model_name: str):
    model = FrenetModel(model_name, PARAMS)
    edge = CONTEXT.w_left_m - CONTEXT.half_width_m
    on_left = model.state_from(edge, 0.1, 3.0, 0.05, 0.4)
    _, _, h = linearised_constraints(
        model_name, PARAM_VALUES, on_left, KAPPA_RADPM, np.zeros(2), CONTEXT
    )
    assert h[0, BARRIER_NAMES.index("lane_left")] == pytest.approx(0.0, abs=1e-12)
    # Mirror the state (e_y, e_psi, v_y, r and the curvature flip sign): left and right swap.
    x = model.state_from(0.2, 0.3, 3.0, 0.1, 0.8)
    mirrored = model.state_from(-0.2, -0.3, 3.0, -0.1, -0.8)
    a, b, h = linearised_constraints(
        model_name, PARAM_VALUES, x, KAPPA_RADPM, np.array([0.05, 1.0]), CONTEXT
    )
    a_m, b_m, h_m = linearised_constraints(
        model_name, PARAM_VALUES, mirrored, -KAPPA_RADPM, np.array([-0.05, 1.0]), CONTEXT
    )
    for left, right in (("lane_left", "lane_right"), ("heading_left", "heading_right")):
        i, j = BARRIER_NAMES.index(left), BARRIER_NAMES.index(right)
        assert h[0, i] == pytest.approx(h_m[0, j])
        assert b[0, i] == pytest.approx(b_m[0, j])
        np.testing.assert_allclose(a[0, i], a_m[0, j] * [-1.0, 1.0], atol=1e-12)  # steering flips


@pytest.mark.parametrize("model_name", ["kinematic", "dynamic", "dynamic-paper"])
@pytest.mark.parametrize("barrier", BARRIER_NAMES)
def test_derived_psi_matches_finite_differences_along_the_model(model_name: str, barrier: str):
    """psi_i = d/dt psi_{i-1} + lam psi_{i-1}, with d/dt taken numerically along the model."""
    condition = hocbf_condition(model_name, barrier)
    model = symbolic_model(model_name)
    numeric = FrenetModel(model_name, PARAMS)
    extra = {
        sp.Symbol(n, real=True): getattr(CONTEXT, f)
        for n, f in (
            ("w_left", "w_left_m"),
            ("w_right", "w_right_m"),
            ("half_width", "half_width_m"),
            ("theta_max", "theta_max_rad"),
            ("w_left_slope", "w_left_slope"),
            ("w_right_slope", "w_right_slope"),
        )
    }
    gains = {sp.Symbol(f"lam_{i}", real=True): g for i, g in enumerate(CONTEXT.gains, start=1)}
    substitutions = {
        model.kappa: KAPPA_RADPM,
        sp.Symbol("lateral_decel", positive=True): CONTEXT.lateral_decel_mps2,
        **gains,
        **extra,
        **dict(zip(model.params, PARAM_VALUES, strict=True)),
    }
    u = np.array([0.08, 0.7])
    functions = [
        sp.lambdify((*model.state, *model.control), psi.subs(substitutions), "math")
        for psi in condition.psi
    ]
    rng = np.random.default_rng(1)
    for _ in range(5):
        x = numeric.state_from(
            rng.uniform(-0.2, 0.2),
            rng.uniform(-0.3, 0.3),
            rng.uniform(2.0, 4.0),
            rng.uniform(-0.1, 0.1),
            rng.uniform(-1.0, 1.0),
        )
        h = 1e-5
        forward = numeric.step(x, u, KAPPA_RADPM, h)
        backward = numeric.step(x, u, KAPPA_RADPM, -h)
        for i in range(1, condition.order + 1):
            previous = functions[i - 1]
            rate = (previous(*forward, *u) - previous(*backward, *u)) / (2 * h)
            expected = rate + class_k_value(barrier, i, CONTEXT.gains[i - 1], previous(*x, *u))
            assert functions[i](*x, *u) == pytest.approx(expected, rel=1e-5, abs=1e-6)


def test_linearisation_is_exact_for_affine_inputs_and_first_order_for_tan():
    x = FrenetModel("dynamic", PARAMS).state_from(0.1, 0.1, 3.0, 0.05, 0.3)
    u0, u1 = np.array([0.05, 0.5]), np.array([0.2, -1.0])
    a0, b0, _ = linearised_constraints("dynamic", PARAM_VALUES, x, KAPPA_RADPM, u0, CONTEXT)
    a1, b1, _ = linearised_constraints("dynamic", PARAM_VALUES, x, KAPPA_RADPM, u1, CONTEXT)
    np.testing.assert_allclose(a0, a1, atol=1e-12)  # psi is affine in u: the same constraint
    np.testing.assert_allclose(b0, b1, atol=1e-9)
    x_kin = FrenetModel("kinematic", PARAMS).state_from(0.1, 0.1, 3.0)
    a0, b0, _ = linearised_constraints("kinematic", PARAM_VALUES, x_kin, KAPPA_RADPM, u0, CONTEXT)
    a1, _, _ = linearised_constraints("kinematic", PARAM_VALUES, x_kin, KAPPA_RADPM, u1, CONTEXT)
    lane = BARRIER_NAMES.index("lane_left")
    assert abs(a1[0, lane, 0]) > abs(a0[0, lane, 0])  # sec^2 of a larger steering angle


@pytest.mark.parametrize("model_name", ["kinematic", "dynamic", "dynamic-paper"])
def test_a_narrowing_lane_moves_the_lane_barrier_at_its_slope_times_s_dot(model_name: str):
    condition = hocbf_condition(model_name, "lane_left")
    model = symbolic_model(model_name)
    slope = sp.Symbol("w_left_slope", real=True)
    first = condition.psi[1]
    assert sp.simplify(sp.diff(first, slope) - model.s_dot) == 0
    # The right lane's slope enters the right barrier only.
    assert not first.has(sp.Symbol("w_right_slope", real=True))
