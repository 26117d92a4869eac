"""Calibrate the state network's MC-dropout spread on frames it never trained on.

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

from saferace.errors import SafeRaceError
from saferace.learning.checkpoint import load_checkpoint, write_text_atomically
from saferace.learning.networks import DrivingNetwork
from saferace.learning.rounds import HELD_OUT_FILE, FrameSet, load_rounds
from saferace.learning.run_layout import RunLayout
from saferace.learning.training import network_data
from saferace.learning.validation import predict_frames
from saferace.track import Track, VehicleEnvelope

#: Floor of a frame's spread in the ratio (a constant output gives no spread at all).
MIN_SPREAD = 1e-6
#: Held-out frames a state network's spread is calibrated on, at least.
MIN_CALIBRATION_FRAMES = 20


def spread_scale(
    state_network: DrivingNetwork, frames: FrameSet, n_samples: int = 10, seed: int = 0
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
