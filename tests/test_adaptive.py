"""Adaptive conformal intervals of the perceived state: oracle and odometry feedback."""

from __future__ import annotations

import numpy as np
import pytest

from saferace.safety.uncertainty.adaptive import ACI_GAMMA, AdaptiveConformalStateSource
from saferace.safety.uncertainty.conformal import ConformalCalibration, calibrate
from saferace.safety.uncertainty.intervals import ConformalStateSource, state_interval
from saferace.track import Track

ALPHA = 0.1


class Scripted:
    """Two samples ``estimate +- std`` per step, from a list of estimates."""

    def __init__(self, estimates: np.ndarray, std: float = 1.0) -> None:
        self.estimates, self.std, self.step = estimates, std, 0

    def reset(self, seed=None) -> None:
        self.step = 0

    def samples(self, observation, info) -> np.ndarray:
        estimate = self.estimates[self.step]
        self.step += 1
        return np.stack([estimate - self.std, estimate + self.std])


def calibrated(source: Scripted, rng: np.random.Generator) -> ConformalStateSource:
    truth = rng.standard_normal((400, 2))
    calibration = calibrate(truth + rng.standard_normal((400, 2)), np.ones((400, 2)), truth, ALPHA)
    return ConformalStateSource(source, calibration)


def observation_and_info(truth: np.ndarray) -> tuple[dict, dict]:
    info = {"e_y_m": truth[0], "e_psi_rad": truth[1], "kappa_radpm": 0.0, "s_m": 1.0}
    return {"velocity": np.zeros(3)}, info


def test_oracle_feedback_holds_the_miss_rate_through_a_shift():
    rng = np.random.default_rng(0)
    steps = 3000
    truths = np.column_stack([rng.standard_normal((steps, 2)), np.zeros(steps)])
    growth = np.where(np.arange(steps) < steps // 3, 1.0, 3.0)[:, None]  # errors triple
    estimates = truths + growth * np.column_stack(
        [rng.standard_normal((steps, 2)), np.zeros(steps)]
    )
    fixed = calibrated(Scripted(estimates), np.random.default_rng(1))
    adaptive = AdaptiveConformalStateSource(
        calibrated(Scripted(estimates.copy()), np.random.default_rng(1)),
        "oracle", Track.load("lab"), 0.05,
    )  # fmt: skip
    fixed_misses, adaptive_misses = [], []
    for truth in truths:
        observation, info = observation_and_info(truth)
        for source, misses in ((fixed, fixed_misses), (adaptive, adaptive_misses)):
            lower, upper = state_interval(source, source.samples(observation, info), z=0.0)
            misses.append(np.any((truth[:2] < lower[:2]) | (truth[:2] > upper[:2])))
    bound = (max(ALPHA, 1 - ALPHA) + ACI_GAMMA) / (ACI_GAMMA * steps)
    assert abs(np.mean(adaptive_misses) - ALPHA) <= bound + 0.01
    assert np.mean(fixed_misses[steps // 3 :]) > 3 * ALPHA  # the fixed interval falls apart
    assert adaptive.describe()["adaptive"]["oracle_feedback"] is True


def test_odometry_feedback_widens_an_estimate_that_jumps_and_narrows_a_steady_one():
    steps = 300
    steady = np.zeros((steps, 3))
    jumping = np.zeros((steps, 3))
    jumping[::2, 0] = 8.0  # e_y jumps 8 spreads every step, the car standing still
    scales = {}
    for name, estimates in (("steady", steady), ("jumping", jumping)):
        source = AdaptiveConformalStateSource(
            calibrated(Scripted(estimates), np.random.default_rng(2)),
            "odometry", Track.load("lab"), 0.05,
        )  # fmt: skip
        start = source.adaptive.scale
        for _ in range(steps):  # as a filter does: samples, then their interval
            state_interval(source, source.samples(*observation_and_info(np.zeros(3))), z=0.0)
        scales[name] = source.adaptive.scale / start
        assert source.describe()["adaptive"]["oracle_feedback"] is False
    assert scales["steady"] < 1.0 < scales["jumping"]


def test_an_adaptive_interval_needs_the_calibration_scores():
    bare = ConformalStateSource(Scripted(np.zeros((1, 3))), ConformalCalibration(0.1, 2.0, 50))
    with pytest.raises(ValueError, match="scores"):
        AdaptiveConformalStateSource(bare, "oracle", Track.load("lab"), 0.05)
    with pytest.raises(ValueError, match="feedback"):
        AdaptiveConformalStateSource(
            calibrated(Scripted(np.zeros((1, 3))), np.random.default_rng(0)),
            "hunch", Track.load("lab"), 0.05,
        )  # fmt: skip
