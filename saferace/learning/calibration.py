"""Calibrate the state network's MC-dropout spread on frames it never trained on.

Two calibrations: variance scaling (below, the baseline) and normalised split conformal
prediction (:func:`fit_conformal`, :mod:`saferace.safety.uncertainty.conformal`), which gives an
interval with a coverage guarantee on exchangeable frames and an out-of-distribution
monitor, stored in the checkpoint for every consumer to use.

Trained on a few hundred frames, the state network's dropout spread is several times
smaller than its error (on lab, the spread of ``e_y`` was 0.01-0.02 m where the error near
the lane's edge was 0.10-0.15 m), so the chance constraints of the probabilistic filter
tighten by centimetres where decimetres were needed. Variance scaling (Laves et al. 2020,
"Well-calibrated regression uncertainty in medical imaging with deep learning") fits one
factor per output, ``s = sqrt(mean(((mean - truth) / spread)^2))`` over held-out frames,
and widens the spread by it; it is floored at 1, so a calibration never narrows a spread.
In DAgger the held-out frames are the part of the latest round's lap past the train
fraction: the network about to drive never trained on any frame there. Only frames with the
whole car inside its lane count: the filter needs the state right while it can still keep
the car in, and a drive that left the lane ends with frames unlike any the network saw.
"""

from __future__ import annotations

import json

import numpy as np

from saferace.errors import ConfigError, SafeRaceError
from saferace.learning.checkpoint import (
    CONFORMAL_KEY,
    load_checkpoint,
    save_with_metadata,
    write_text_atomically,
)
from saferace.learning.ensemble import StateNetwork
from saferace.learning.rounds import HELD_OUT_FILE, FrameSet, load_rounds
from saferace.learning.run_layout import RunLayout
from saferace.learning.training_data import network_data
from saferace.learning.validation import predict_frames
from saferace.names import DEFAULT_MONITOR, OOD_MONITORS
from saferace.safety.uncertainty.conformal import ConformalCalibration, calibrate
from saferace.track import Track, VehicleEnvelope

#: Floor of a frame's spread in the ratio (a constant output gives no spread at all).
MIN_SPREAD = 1e-6
#: The outputs a conformal calibration covers: the lane state the barriers need (the robust
#: filter takes the curvature from the map).
CALIBRATED_OUTPUTS = ("e_y_m", "e_psi_rad")
#: Held-out frames a state network's spread is calibrated on, at least.
MIN_CALIBRATION_FRAMES = 20


def spread_scale(
    state_network: StateNetwork, frames: FrameSet, n_samples: int = 10, seed: int = 0
) -> np.ndarray:
    """Per-output factors ``>= 1`` that make the network's spread match its error on
    ``frames`` (RMS of the error in spreads)."""
    if not len(frames):
        raise SafeRaceError("calibrating the state network's spread needs at least one frame")
    data = network_data(frames)["state"]
    prediction = predict_frames(state_network, data, n_samples, seed=seed)
    ratio = (prediction.mean - data.targets) / np.maximum(prediction.std, MIN_SPREAD)
    return np.maximum(np.sqrt(np.mean(ratio**2, axis=0)), 1.0)


def inside_lane(
    frames: FrameSet, track: Track, car_width_m: float = VehicleEnvelope.width_m
) -> np.ndarray:
    """Frames whose car (``car_width_m`` wide) lies wholly inside the lane of ``track``."""
    e_y = frames["state"][:, 0]
    w_right, w_left = track.widths(frames["s_m"])
    half = 0.5 * car_width_m
    return (e_y + half <= w_left) & (e_y - half >= -w_right)


def spread_scale_of(
    layout: RunLayout, iteration: int, mc_samples: int, seed: int
) -> tuple[float, float, float]:
    """The calibration of the state network of a run's ``iteration``, fitted on the held-out
    frames (the part of the lap it never trained on, with the car inside its lane) of the
    latest round that has at least :data:`MIN_CALIBRATION_FRAMES` of them; written once
    beside the checkpoint, read back afterwards."""
    path = layout.spread_scale(iteration)
    if not path.exists():
        network = load_checkpoint(layout.checkpoint(iteration)).state
        for previous in range(iteration - 1, -1, -1):
            round_dir = layout.round(previous)
            manifest = json.loads(layout.manifest(previous).read_text())
            if manifest.get("held_out_frame_count", 0) < MIN_CALIBRATION_FRAMES:
                continue
            frames = load_rounds([round_dir], held_out=True)
            track = Track.load(manifest["config"]["track_argument"])
            inside = inside_lane(frames, track)
            if inside.sum() >= MIN_CALIBRATION_FRAMES:
                break
        else:
            raise SafeRaceError(
                f"no round of {layout.root} holds {MIN_CALIBRATION_FRAMES} held-out frames with "
                "the car inside its lane to calibrate the state network on (is the train "
                "fraction below 1?)"
            )
        scale = spread_scale(network, frames.subset(inside), mc_samples, seed=seed)
        record = {
            "spread_scale": scale.tolist(),
            "fitted_on": f"{round_dir.name} ({HELD_OUT_FILE})",
            "frames": int(inside.sum()),
        }
        write_text_atomically(path, json.dumps(record, indent=2) + "\n")
    return tuple(json.loads(path.read_text())["spread_scale"])


def fit_conformal(
    state_network: StateNetwork,
    frames: FrameSet,
    alpha: float = 0.05,
    n_samples: int = 10,
    seed: int = 0,
    monitor: str = DEFAULT_MONITOR,
) -> ConformalCalibration:
    """The network's conformal calibration of :data:`CALIBRATED_OUTPUTS` (interval scale and
    the ``monitor``, on the network's ``features`` or on its ``spread`` or ``none``, both at
    ``alpha``) on ``frames`` it never trained on, with ``n_samples`` MC-dropout samples (as
    many as the state source that will use it draws)."""
    if monitor not in OOD_MONITORS:
        raise ConfigError("monitor", f"must be one of {OOD_MONITORS}, got {monitor!r}")
    if len(frames) < MIN_CALIBRATION_FRAMES:
        raise SafeRaceError(
            f"a conformal calibration needs at least {MIN_CALIBRATION_FRAMES} frames the "
            f"network never trained on, got {len(frames)}"
        )
    data = network_data(frames)["state"]
    prediction = predict_frames(state_network, data, n_samples, seed=seed)
    lane = slice(0, len(CALIBRATED_OUTPUTS))
    return calibrate(
        prediction.mean[:, lane],
        prediction.std[:, lane],
        data.targets[:, lane],
        alpha,
        None if monitor == "none" else alpha,
        prediction.features if monitor == "features" else None,
    )


def conformal_of(
    layout: RunLayout, iteration: int, alpha: float, mc_samples: int, seed: int
) -> dict:
    """The conformal calibration of the state network of a run's ``iteration``, fitted on
    the held-out frames of every earlier round (the part of the lap no network of the run
    trained on) with the car inside its lane, and written into the checkpoint once."""
    path = layout.checkpoint(iteration)
    loaded = load_checkpoint(path)
    if CONFORMAL_KEY in loaded.metadata:
        return loaded.metadata[CONFORMAL_KEY]
    rounds = [layout.round(previous) for previous in range(iteration)]
    frames = load_rounds(rounds, held_out=True)
    manifest = json.loads(layout.manifest(0).read_text())  # a run drives one track
    inside = frames.subset(inside_lane(frames, Track.load(manifest["config"]["track_argument"])))
    if len(inside) < MIN_CALIBRATION_FRAMES:
        raise SafeRaceError(
            f"the rounds of {layout.root} hold {len(inside)} held-out frames with the car "
            f"inside its lane, fewer than the {MIN_CALIBRATION_FRAMES} a calibration of the "
            "state network needs (is the train fraction below 1?)"
        )
    calibration = fit_conformal(loaded.state, inside, alpha, mc_samples, seed)
    record = {**calibration.as_dict(), "fitted_on": f"rounds 0-{iteration - 1} ({HELD_OUT_FILE})"}
    save_with_metadata(path, {CONFORMAL_KEY: record}, path)
    return record
