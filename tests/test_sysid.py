"""System identification recovers known parameters from data the models generate themselves."""

from __future__ import annotations

import numpy as np
import pytest

from saferace.safety.models import FrenetModel
from saferace.safety.vehicle_params import VehicleParams
from saferace.sysid.fit import (
    first_order_response,
    fit_lateral,
    fit_longitudinal,
    fit_time_constant,
    interval_mean,
    interval_rate,
)

TRUE = VehicleParams(
    yaw_inertia_kgm2=0.085, cf0_npr=15.0, df_nspmr=190.0, cr0_npr=25.0, dr_nspmr=220.0
)


def simulate_dynamic(
    speed: float, seconds: float = 4.0, dt: float = 0.002
) -> dict[str, np.ndarray]:
    """A chirp-steered run of the dynamic model, logged every ``dt`` with the steering held."""
    model = FrenetModel("dynamic", TRUE)
    t = np.arange(0.0, seconds, dt)
    steer = 0.08 * np.sin(2 * np.pi * (0.3 * t + 0.4 * t * t))  # chirp 0.3 -> 3.5 Hz
    x = np.array([0.0, 0.0, speed, 0.0, 0.0])
    rows = []
    for k in range(len(t)):
        rows.append(x.copy())
        x = model.step(x, np.array([steer[k], 0.0]), 0.0, dt)
    states = np.asarray(rows)
    return {"t": t, "steer": steer, "v_x": states[:, 2], "v_y": states[:, 3], "r": states[:, 4]}


def test_lateral_fit_recovers_tyres_and_inertia():
    logs = [simulate_dynamic(v) for v in (1.5, 3.0, 4.5)]

    def intervals(signal) -> np.ndarray:
        return np.concatenate([signal(log) for log in logs])

    fit = fit_lateral(
        v_x=intervals(lambda log: interval_mean(log["v_x"])),
        v_y=intervals(lambda log: interval_mean(log["v_y"])),
        r=intervals(lambda log: interval_mean(log["r"])),
        steer_rad=intervals(lambda log: log["steer"][:-1]),  # held over each interval
        v_y_dot=intervals(lambda log: interval_rate(log["t"], log["v_y"])),
        r_dot=intervals(lambda log: interval_rate(log["t"], log["r"])),
        mass_kg=TRUE.mass_kg,
        lf_m=TRUE.lf_m,
        lr_m=TRUE.lr_m,
    )
    # C_0 and D trade off over a narrow speed range; the stiffness at each driven speed is
    # what the data pins down.
    for v in (1.5, 3.0, 4.5):
        assert fit.cf0_npr + fit.df_nspmr * v == pytest.approx(
            TRUE.cf0_npr + TRUE.df_nspmr * v, rel=0.01
        )
        assert fit.cr0_npr + fit.dr_nspmr * v == pytest.approx(
            TRUE.cr0_npr + TRUE.dr_nspmr * v, rel=0.01
        )
    assert fit.yaw_inertia_kgm2 == pytest.approx(TRUE.yaw_inertia_kgm2, rel=0.01)


def test_time_constant_of_a_first_order_lag():
    t = np.arange(0.0, 3.0, 0.01)
    command = np.where((t % 1.0) < 0.5, 0.2, -0.1)
    actual = first_order_response(t, command, 0.06, 0.0)
    assert fit_time_constant(t, command, actual) == pytest.approx(0.06, rel=0.01)


def sampled_longitudinal_run(
    t: np.ndarray, command: np.ndarray, lag_s: float, gain: float, drag_per_s: float
) -> np.ndarray:
    """``v' = gain * lag(command) - drag * v`` integrated 100 times finer than ``t`` is
    sampled, with the command held between samples and the lag settled on its first value."""
    substeps = 100
    dt_s = float(t[1] - t[0]) / substeps
    fine_t = np.arange(len(t) * substeps) * dt_s
    fine_command = np.repeat(command, substeps)
    realised = first_order_response(fine_t, fine_command, lag_s, command[0])
    v = np.empty_like(fine_t)
    v[0] = 1.0
    for k in range(1, len(fine_t)):
        v[k] = v[k - 1] + (gain * realised[k - 1] - drag_per_s * v[k - 1]) * dt_s
    return v[::substeps]


def test_longitudinal_fit_recovers_lag_gain_and_drag():
    t = np.arange(0.0, 6.0, 0.01)
    command = np.where(t < 2.0, 3.0, np.where(t < 3.5, -2.5, 1.0))
    v = sampled_longitudinal_run(t, command, lag_s=0.05, gain=0.9, drag_per_s=0.08)
    fit = fit_longitudinal(t, v, np.zeros_like(t), np.zeros_like(t), command)
    assert fit.gain == pytest.approx(0.9, rel=0.01)
    assert fit.drag_per_s == pytest.approx(0.08, rel=0.01)
    assert fit.time_constant_s == pytest.approx(0.05, rel=0.01)
