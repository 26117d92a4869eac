"""What ``saferace calibrate`` does: fit a checkpoint's conformal calibration on rounds and
check it on frames it did not use.

The rounds' frames are split at random (seeded): ``1 - test_share`` of them fit the
interval scale and the monitor, the rest measure what a consumer will get. On those test
frames the table compares the state network's own interval (``mean +- z std`` of its
MC-dropout or ensemble spread at the calibration's level, what the chance constraints
assume) with the calibrated one:
coverage of ``e_y`` and ``e_psi`` together (what the calibration covers: the robust filter
takes the curvature from the map) with its Clopper-Pearson 95% band, the mean half width of
``e_y``, and the share of frames the monitor raised on. The frames should be ones the
network never trained on (other rounds, another track, another look).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.stats import norm

from saferace.errors import ConfigError
from saferace.learning.agent import check_image_shape
from saferace.learning.calibration import CALIBRATED_OUTPUTS, fit_conformal
from saferace.learning.checkpoint import CONFORMAL_KEY, load_checkpoint, save_with_metadata
from saferace.learning.networks import Prediction
from saferace.learning.rounds import load_rounds
from saferace.learning.training_data import network_data
from saferace.learning.validation import predict_frames
from saferace.names import DEFAULT_MONITOR
from saferace.safety.uncertainty.conformal import Monitor, SpreadMonitor, coverage


def recalibrate(
    checkpoint: str | Path,
    data_paths: list[str | Path],
    out: str | Path,
    alpha: float = 0.05,
    mc_samples: int = 10,
    test_share: float = 0.5,
    seed: int = 0,
    monitor: str = DEFAULT_MONITOR,
) -> list[dict]:
    """Write ``checkpoint`` with a conformal calibration fitted on ``data_paths`` (and its
    out-of-distribution ``monitor``, see :data:`saferace.names.OOD_MONITORS`) to ``out``; the
    rows of the test frames' table (see the module)."""
    if not 0.0 < test_share < 1.0:
        raise ConfigError("test_share", f"must be in (0, 1), got {test_share}")
    loaded = load_checkpoint(checkpoint)
    frames = load_rounds(data_paths)
    check_image_shape(loaded, frames["image"].shape[1:])
    test = np.random.default_rng(seed).random(len(frames)) < test_share
    calibration = fit_conformal(
        loaded.state, frames.subset(~test), alpha, mc_samples, seed, monitor=monitor
    )
    data = network_data(frames.subset(test))["state"]
    prediction = predict_frames(loaded.state, data, mc_samples, seed=seed + 1)
    z = float(norm.ppf(1.0 - 0.5 * alpha))
    intervals = {
        f"its own spread, mean +- {z:.2f} std": (z, None),
        f"conformal, mean +- {calibration.scale:.2f} std": (calibration.scale, calibration),
    }
    rows = []
    for method, (scale, calibrated) in intervals.items():
        lower, upper = (
            prediction.mean - scale * prediction.std,
            prediction.mean + scale * prediction.std,
        )
        lane = slice(0, len(CALIBRATED_OUTPUTS))
        covered, (low, high) = coverage(lower[:, lane], upper[:, lane], data.targets[:, lane])
        alarms = None if calibrated is None else alarm_rate(calibrated.monitor, prediction)
        rows.append(
            {
                "interval": method,
                "test frames": len(data),
                "coverage": covered,
                "coverage 95% band": f"{low:.3f}-{high:.3f}",
                "target": 1.0 - alpha,
                "mean e_y half width [m]": float(np.mean(scale * prediction.std[:, 0])),
                "monitor alarm rate": alarms,
            }
        )
    record = {
        **calibration.as_dict(),
        "fitted_on": [str(path) for path in data_paths],
        "test_coverage": rows[-1]["coverage"],
    }
    save_with_metadata(checkpoint, {CONFORMAL_KEY: record}, out)
    return rows


def alarm_rate(monitor: Monitor | None, prediction: Prediction) -> float | None:
    """The share of ``prediction``'s frames ``monitor`` raises on (None: no monitor)."""
    if monitor is None:
        return None
    if isinstance(monitor, SpreadMonitor):
        lane = slice(0, len(monitor.reference))
        return float(np.mean([monitor.raises(spread[lane])[1] for spread in prediction.std]))
    return float(np.mean(monitor.scores(prediction.features) > monitor.threshold))
