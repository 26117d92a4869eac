"""Calibrating the state network's spread: the factor that makes the spread match the error."""

from __future__ import annotations

import numpy as np
import pytest

from saferace.errors import SafeRaceError
from saferace.learning.calibration import spread_scale
from saferace.learning.networks import Prediction
from saferace.learning.rounds import FRAME_FIELDS, FrameSet

FRAMES = 40
TRUTH = np.column_stack(
    [np.linspace(-0.3, 0.3, FRAMES), np.linspace(0.2, -0.2, FRAMES), np.full(FRAMES, 0.5)]
)


class OffByKnownAmounts:
    """A state network whose mean misses the truth by ``+-error`` on half the frames and
    ``+-2 error`` on the others, with spread ``spread``; a frame's index is its image's
    first pixel."""

    def __init__(self, error: np.ndarray, spread: np.ndarray) -> None:
        self.error, self.spread = error, spread

    def predict(self, images, velocity, n_samples, generator) -> Prediction:
        index = np.asarray(images)[:, 0, 0, 0].astype(int)
        sign = np.where(index % 2 == 0, 1.0, -1.0)  # a bias both ways
        size = np.where(index % 4 < 2, 1.0, 2.0)
        mean = TRUTH[index] + (sign * size)[:, None] * self.error
        std = np.broadcast_to(self.spread, mean.shape)
        samples = mean[:, None, :] + np.zeros((1, n_samples, 1))
        return Prediction(mean, std, samples, mean.copy())


def frames(count: int = FRAMES) -> FrameSet:
    arrays = {
        name: np.zeros((count, *(shape or (2, 2, 3))), dtype) for name, (dtype, shape) in
        FRAME_FIELDS.items()
    }  # fmt: skip
    arrays["image"][:, 0, 0, 0] = np.arange(count)
    arrays["state"] = TRUTH[:count].astype(np.float32)
    return FrameSet(arrays, [])


def test_the_factor_is_the_error_in_spreads_and_never_narrows():
    network = OffByKnownAmounts(np.array([0.2, 0.1, 0.02]), np.array([0.1, 0.5, 0.01]))
    scale = spread_scale(network, frames(), n_samples=4)
    rms_in_spreads = np.sqrt((1.0 + 4.0) / 2.0) * np.array([2.0, 0.2, 2.0])
    assert scale == pytest.approx([rms_in_spreads[0], 1.0, rms_in_spreads[2]], rel=1e-5)


def test_no_frames_is_refused():
    network = OffByKnownAmounts(np.zeros(3), np.ones(3))
    with pytest.raises(SafeRaceError, match="at least one frame"):
        spread_scale(network, frames(0))
