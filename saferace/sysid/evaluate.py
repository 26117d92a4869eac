"""Open-loop prediction error of the vehicle models against logged MuJoCo runs."""

from __future__ import annotations

import numpy as np

from saferace.safety.models import FrenetModel
from saferace.sysid.fit import interval_mean, interval_rate

HORIZON_S = 0.5
WINDOW_STRIDE_S = 0.1


def prediction_errors(
    model: FrenetModel, log: dict[str, np.ndarray], horizon_s: float = HORIZON_S
) -> dict[str, float]:
    """RMS errors in ``e_y`` (m) and ``e_psi`` (rad) after ``horizon_s`` of open-loop prediction.

    Windows start every 0.1 s after the first 0.5 s. Inputs are the measured wheel angle
    and the measured longitudinal acceleration over each sample interval, so the error is the
    model's alone.
    """
    t = log["t_s"]
    dt = float(np.median(np.diff(t)))
    steps = round(horizon_s / dt)
    accel = interval_rate(t, log["v_x"]) - interval_mean(log["v_y"] * log["r"])
    starts = range(round(0.5 / dt), len(t) - steps, max(1, round(WINDOW_STRIDE_S / dt)))
    e_y_errors, e_psi_errors = [], []
    for i in starts:
        x = model.state_from(
            log["e_y"][i], log["e_psi"][i], log["v_x"][i], log["v_y"][i], log["r"][i]
        )
        for k in range(i, i + steps):
            x = model.step(
                x, np.array([log["steer_actual"][k], accel[k]]), log["kappa"][k], t[k + 1] - t[k]
            )
        e_y_errors.append(x[0] - log["e_y"][i + steps])
        e_psi_errors.append(x[1] - log["e_psi"][i + steps])
    return {
        "rms_e_y_m": float(np.sqrt(np.mean(np.square(e_y_errors)))),
        "rms_e_psi_rad": float(np.sqrt(np.mean(np.square(e_psi_errors)))),
        "windows": len(e_y_errors),
    }
