"""Identify the rc10's model parameters from MuJoCo runs; report each model's prediction error."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from saferace.names import VEHICLE_MODELS
from saferace.safety.models import FrenetModel
from saferace.safety.vehicle_params import VehicleParams
from saferace.sysid.evaluate import prediction_errors
from saferace.sysid.fit import (
    fit_lateral,
    fit_longitudinal,
    fit_time_constant,
    interval_mean,
    interval_rate,
)
from saferace.sysid.manoeuvres import collect

LATERAL_MIN_SPEED_MPS = 1.0
SETTLE_S = 0.3
EVALUATION_LOGS = {"low speed (1.5 m/s)": "sweep_1.5", "racing speed (4.5 m/s)": "sweep_4.5"}
MODELS = VEHICLE_MODELS


@dataclass(frozen=True)
class IdentificationResult:
    """Identified parameters, fit residuals and prediction errors per (speed, model)."""

    params: VehicleParams
    residuals: dict[str, float]
    prediction: dict[str, dict[str, dict[str, float]]]

    def report(self) -> dict:
        return {"residuals": self.residuals, "prediction_error_0p5s": self.prediction}


def identify() -> IdentificationResult:
    """Collect the standard manoeuvres, fit every parameter, and evaluate the models."""
    logs, geometry = collect()
    lateral_logs = [log for name, log in logs.items() if not name.startswith("accel")]

    def over_intervals(signal) -> np.ndarray:
        """``signal(log)`` over the sample intervals of the lateral logs, settled and rolling."""
        parts = []
        for log in lateral_logs:
            keep = (interval_mean(log["t_s"]) > SETTLE_S) & (
                interval_mean(log["v_x"]) > LATERAL_MIN_SPEED_MPS
            )
            parts.append(signal(log)[keep])
        return np.concatenate(parts)

    steer_tau = float(
        np.median(
            [
                fit_time_constant(log["t_s"], log["steer_target"], log["steer_actual"])
                for log in lateral_logs
            ]
        )
    )
    lateral = fit_lateral(
        v_x=over_intervals(lambda log: interval_mean(log["v_x"])),
        v_y=over_intervals(lambda log: interval_mean(log["v_y"])),
        r=over_intervals(lambda log: interval_mean(log["r"])),
        steer_rad=over_intervals(lambda log: interval_mean(log["steer_actual"])),
        v_y_dot=over_intervals(lambda log: interval_rate(log["t_s"], log["v_y"])),
        r_dot=over_intervals(lambda log: interval_rate(log["t_s"], log["r"])),
        mass_kg=geometry["mass_kg"],
        lf_m=geometry["lf_m"],
        lr_m=geometry["lr_m"],
    )
    accel_log = logs["accel_brake"]
    longitudinal = fit_longitudinal(
        accel_log["t_s"], accel_log["v_x"], accel_log["v_y"], accel_log["r"], accel_log["accel_cmd"]
    )
    params = VehicleParams(
        mass_kg=geometry["mass_kg"],
        yaw_inertia_kgm2=lateral.yaw_inertia_kgm2,
        lf_m=geometry["lf_m"],
        lr_m=geometry["lr_m"],
        cf0_npr=lateral.cf0_npr,
        df_nspmr=lateral.df_nspmr,
        cr0_npr=lateral.cr0_npr,
        dr_nspmr=lateral.dr_nspmr,
        steer_time_constant_s=steer_tau,
        accel_time_constant_s=longitudinal.time_constant_s,
        accel_gain=longitudinal.gain,
        drag_per_s=longitudinal.drag_per_s,
    )
    residuals = {
        "lateral_rms_mps2": lateral.rms_residual_lateral_mps2,
        "yaw_rms_radps2": lateral.rms_residual_yaw_radps2,
        "longitudinal_rms_mps2": longitudinal.rms_residual_mps2,
    }
    prediction = {
        label: {
            name: prediction_errors(FrenetModel(name, params), logs[log_name]) for name in MODELS
        }
        for label, log_name in EVALUATION_LOGS.items()
    }
    return IdentificationResult(params, residuals, prediction)


def as_dict(result: IdentificationResult) -> dict:
    return {"params": asdict(result.params), **result.report()}
