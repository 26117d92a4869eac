"""Vehicle models: Jacobians against finite differences, and hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import expm

from saferace.safety.models import SYMBOLIC_MODELS, FrenetModel
from saferace.safety.vehicle_params import VehicleParams

PARAMS = VehicleParams(
    cf0_npr=20.0, df_nspmr=150.0, cr0_npr=30.0, dr_nspmr=180.0, yaw_inertia_kgm2=0.08
)
MODEL_NAMES = sorted(SYMBOLIC_MODELS)


def random_state(model: FrenetModel, rng: np.random.Generator) -> np.ndarray:
    ranges = {
        "e_y": (-0.4, 0.4),
        "e_psi": (-0.5, 0.5),
        "v": (1.0, 6.0),
        "v_x": (1.0, 6.0),
        "v_y": (-0.4, 0.4),
        "r": (-3.0, 3.0),
    }
    return np.array([rng.uniform(*ranges[name]) for name in model.state_names])


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_jacobians_match_finite_differences(name: str):
    model = FrenetModel(name, PARAMS)
    rng = np.random.default_rng(0)
    for _ in range(20):
        x, u, kappa = (
            random_state(model, rng),
            rng.uniform([-0.3, -3.0], [0.3, 3.0]),
            rng.uniform(-0.8, 0.8),
        )
        a, b = model.jacobians(x, u, kappa)
        h = 1e-6
        a_fd = np.column_stack(
            [
                (model.f(x + h * e, u, kappa) - model.f(x - h * e, u, kappa)) / (2 * h)
                for e in np.eye(model.n_state)
            ]
        )
        b_fd = np.column_stack(
            [
                (model.f(x, u + h * e, kappa) - model.f(x, u - h * e, kappa)) / (2 * h)
                for e in np.eye(model.n_control)
            ]
        )
        np.testing.assert_allclose(a, a_fd, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(b, b_fd, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_straight_line_at_constant_speed_is_an_equilibrium(name: str):
    model = FrenetModel(name, PARAMS)
    x = np.zeros(model.n_state)
    x[model.speed_index] = 3.0
    np.testing.assert_allclose(model.f(x, np.zeros(2), 0.0), 0.0, atol=1e-12)
    assert model.s_dot(x, 0.0) == pytest.approx(3.0)
    # Pure acceleration changes only the speed.
    derivative = model.f(x, np.array([0.0, 1.5]), 0.0)
    assert derivative[model.speed_index] == pytest.approx(1.5)
    assert np.count_nonzero(derivative) == 1


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_along_track_speeds_over_one_less_kappa_e_y_are_s_dot(name: str):
    """The vectorised numerator of ``s_dot`` (many stages in one call) gives ``s_dot`` at
    any curvature, the raised speed of a car below ``MIN_SPEED_MPS`` included."""
    model = FrenetModel(name, PARAMS)
    rng = np.random.default_rng(4)
    states = np.array([random_state(model, rng) for _ in range(8)])
    states[0, model.speed_index] = 0.1
    speeds = model.along_track_speeds_mps(states)
    for x, speed in zip(states, speeds, strict=True):
        kappa = rng.uniform(-1.0, 1.0)
        assert speed / (1.0 - kappa * x[0]) == pytest.approx(model.s_dot(x, kappa), rel=1e-12)


def test_kinematic_steady_circle():
    model = FrenetModel("kinematic", PARAMS)
    kappa, v = 0.5, 2.0
    steer = math.atan(PARAMS.wheelbase_m * kappa)  # v tan(delta) / L = v kappa
    np.testing.assert_allclose(
        model.f(np.array([0.0, 0.0, v, 0.0]), np.array([steer, 0.0]), kappa), 0.0, atol=1e-12
    )
    # Off the centerline the reference turns at s_dot kappa with s_dot = v / (1 - kappa e_y).
    e_y = 0.2
    rate = model.f(np.array([e_y, 0.0, v, 0.0]), np.array([steer, 0.0]), kappa)[1]
    assert rate == pytest.approx(v * kappa - kappa * v / (1 - kappa * e_y))


def test_dynamic_steady_circle_from_hand_computed_trim():
    """Solve the single-track trim (v_y, delta) by hand for r = kappa * V and check f = 0."""
    p, v_x, kappa = PARAMS, 3.0, 0.4
    c_f, c_r = p.cf0_npr + p.df_nspmr * v_x, p.cr0_npr + p.dr_nspmr * v_x
    m, i_z, l_f, l_r = p.mass_kg, p.yaw_inertia_kgm2, p.lf_m, p.lr_m
    # Unknowns v_y, delta and r with r = kappa * sqrt(v_x^2 + v_y^2): iterate the 2x2 linear solve.
    v_y = 0.0
    for _ in range(50):
        r = kappa * math.hypot(v_x, v_y)
        lhs = np.array(
            [
                [-(c_f + c_r) / (m * v_x), c_f / m],
                [(l_r * c_r - l_f * c_f) / (i_z * v_x), l_f * c_f / i_z],
            ]
        )
        rhs = -np.array(
            [
                ((l_r * c_r - l_f * c_f) / (m * v_x) - v_x) * r,
                -(l_f**2 * c_f + l_r**2 * c_r) / (i_z * v_x) * r,
            ]
        )
        v_y, delta = np.linalg.solve(lhs, rhs)
    e_psi = -math.atan2(v_y, v_x)  # velocity along the centerline: e_y stays 0
    x = np.array([0.0, e_psi, v_x, v_y, r])
    derivative = FrenetModel("dynamic", PARAMS).f(x, np.array([delta, -v_y * r]), kappa)
    np.testing.assert_allclose(derivative, 0.0, atol=1e-9)


def test_paper_model_drops_the_steering_path_to_lateral_velocity():
    x = np.array([0.0, 0.0, 3.0, 0.1, 0.5])
    _, b_full = FrenetModel("dynamic", PARAMS).jacobians(x, np.zeros(2), 0.2)
    _, b_paper = FrenetModel("dynamic-paper", PARAMS).jacobians(x, np.zeros(2), 0.2)
    v_y = 3
    assert b_full[v_y, 0] > 0.0 and b_paper[v_y, 0] == 0.0


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_discretisation_is_the_exact_zero_order_hold(name: str):
    model = FrenetModel(name, PARAMS)
    x, u, kappa, dt = random_state(model, np.random.default_rng(2)), np.array([0.1, 0.5]), 0.3, 0.05
    a_d, b_d, c_d = model.discretize(x, u, kappa, dt)
    a, _ = model.jacobians(x, u, kappa)
    np.testing.assert_allclose(a_d, expm(a * dt), rtol=1e-9, atol=1e-12)
    # A_d x + B_d u + c_d solves the linearised affine ODE exactly (fine RK4 as the reference).
    b = model.jacobians(x, u, kappa)[1]
    c = model.f(x, u, kappa) - a @ x - b @ u
    y, h = x.copy(), dt / 2000
    for _ in range(2000):
        k1 = a @ y + b @ u + c
        k2 = a @ (y + h / 2 * k1) + b @ u + c
        k3 = a @ (y + h / 2 * k2) + b @ u + c
        k4 = a @ (y + h * k3) + b @ u + c
        y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    np.testing.assert_allclose(a_d @ x + b_d @ u + c_d, y, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_every_stage_with_the_steering_lag_is_its_own_exact_zero_order_hold(name: str):
    """The batched discretisation of a horizon gives each stage what the lagged system of
    that stage alone gives: the model seeing the wheels' angle, which lags the command."""
    model, rng, dt, tau = FrenetModel(name, PARAMS), np.random.default_rng(5), 0.05, 0.04
    n = model.n_state
    xs = np.array([[*random_state(model, rng), rng.uniform(-0.2, 0.2)] for _ in range(4)])
    us, kappas = rng.uniform(-0.3, 0.3, (4, 2)), rng.uniform(-0.5, 0.5, 4)
    a_d, b_d, c_d = model.discretize_stages_with_steering_lag(xs, us, kappas, dt, tau)
    for k in range(4):
        applied = np.array([xs[k, n], us[k, 1]])
        a, b = model.jacobians(xs[k, :n], applied, kappas[k])
        lagged_a = np.zeros((n + 1, n + 1))
        lagged_a[:n, :n], lagged_a[:n, n], lagged_a[n, n] = a, b[:, 0], -1.0 / tau
        lagged_b = np.zeros((n + 1, 2))
        lagged_b[:n, 1], lagged_b[n, 0] = b[:, 1], 1.0 / tau
        derivative = np.append(model.f(xs[k, :n], applied, kappas[k]), (us[k, 0] - xs[k, n]) / tau)
        block = np.zeros((n + 4, n + 4))  # [[A, B, c], [0, 0, 0]]: the exact zero-order hold
        block[: n + 1, : n + 1], block[: n + 1, n + 1 : n + 3] = lagged_a, lagged_b
        block[: n + 1, -1] = derivative - lagged_a @ xs[k] - lagged_b @ us[k]
        exact = expm(block * dt)
        np.testing.assert_allclose(a_d[k], exact[: n + 1, : n + 1], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(b_d[k], exact[: n + 1, n + 1 : n + 3], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(c_d[k], exact[: n + 1, -1], rtol=1e-9, atol=1e-12)
