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

import numpy as np

from saferace.errors import SafeRaceError
from saferace.learning.networks import DrivingNetwork
from saferace.learning.rounds import FrameSet
from saferace.learning.training import network_data
from saferace.learning.validation import predict_frames
from saferace.track import Track, VehicleEnvelope

#: Floor of a frame's spread in the ratio (a constant output gives no spread at all).
MIN_SPREAD = 1e-6


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
