"""The out-of-distribution monitor on the state network's features: it raises on at most
alpha of exchangeable frames, on nearly every frame of a shifted look, and it is what a
calibrated learned source consults."""

from __future__ import annotations

import math

import numpy as np
import pytest

from saferace.errors import SafeRaceError
from saferace.safety.uncertainty.conformal import ConformalCalibration, fit_feature_monitor
from saferace.safety.uncertainty.feature_monitor import FeatureMonitor, feature_monitor
from saferace.safety.uncertainty.intervals import ConformalStateSource

ALPHA = 0.05
FEATURES = 64


def look(rng: np.random.Generator, n: int, shift: float = 0.0) -> np.ndarray:
    """Features of ``n`` frames: a few strong directions (the lane's geometry) over weak
    noise; ``shift`` moves every frame off the fitted subspace (a new look)."""
    directions = np.linspace(1.0, 2.0, FEATURES * 4).reshape(4, FEATURES)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    geometry = rng.normal(0.0, 3.0, (n, 4)) @ directions
    offset = shift * np.sin(np.arange(FEATURES))  # mostly outside the strong directions
    return geometry + rng.normal(0.0, 0.3, (n, FEATURES)) + offset


def test_the_feature_monitor_raises_on_at_most_alpha_of_exchangeable_frames():
    rng = np.random.default_rng(0)
    rates = []
    for _ in range(200):
        monitor = fit_feature_monitor(look(rng, 300), ALPHA, seed=int(rng.integers(1 << 30)))
        rates.append(np.mean(monitor.scores(look(rng, 400)) > monitor.threshold))
    spread = np.std(rates) / math.sqrt(len(rates))
    assert np.mean(rates) <= ALPHA + 3 * spread
    assert np.mean(rates) >= ALPHA - 1 / 150 - 3 * spread  # and not needlessly quiet


def test_the_feature_monitor_raises_on_a_new_look_its_spread_would_not_see():
    rng = np.random.default_rng(1)
    monitor = fit_feature_monitor(look(rng, 300), ALPHA)
    shifted = monitor.scores(look(rng, 200, shift=1.0))
    assert np.mean(shifted > monitor.threshold) > 0.95
    # the strong directions alone (a new place on the same look) raise no more than alpha
    assert np.mean(monitor.scores(look(rng, 400)) > monitor.threshold) < 2 * ALPHA


def test_the_score_is_the_mahalanobis_distance_in_the_subspace_plus_the_residual():
    features = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, -2.0, 0.0]])
    monitor = feature_monitor(features, ALPHA, components=1)
    # the kept direction is the second axis (variance 8/3); the residual's energy is 2/4 a frame
    assert monitor.scores(np.array([[0.0, 4.0, 0.0]]))[0] == pytest.approx(16 / (8 / 3))
    assert monitor.scores(np.array([[1.0, 0.0, 0.0]]))[0] == pytest.approx(1 / 0.5)
    with pytest.raises(SafeRaceError, match="fitted on 3 features"):
        monitor.scores(np.zeros((1, 4)))


def test_a_feature_monitor_survives_the_round_trip_and_rows_record_no_arrays():
    rng = np.random.default_rng(2)
    calibration = ConformalCalibration(0.05, 3.0, 300, fit_feature_monitor(look(rng, 300)))
    assert ConformalCalibration.from_dict(calibration.as_dict()) == calibration
    summary = calibration.summary()["monitor"]
    assert summary["kind"] == "features" and summary["features"] == FEATURES
    assert summary["components"] == 16 and "mean" not in summary
    assert all(np.isscalar(value) for value in summary.values())


class FeatureState:
    """A learned source's stand-in: fixed samples, the features of its last frame."""

    def __init__(self, features: np.ndarray | None) -> None:
        self.last_features = features

    def reset(self, seed: int | None = None) -> None:
        pass

    def samples(self, observation, info) -> np.ndarray:
        return np.zeros((4, 3))


def test_a_calibrated_source_asks_the_monitor_about_the_last_frame_it_saw():
    rng = np.random.default_rng(3)
    fitted = look(rng, 300)
    monitor: FeatureMonitor = fit_feature_monitor(fitted, ALPHA)
    calibration = ConformalCalibration(0.05, 3.0, 300, monitor)
    samples = np.zeros((4, 3))
    calm = ConformalStateSource(FeatureState(fitted.mean(axis=0)), calibration)
    shifted = ConformalStateSource(FeatureState(look(rng, 1, shift=2.0)[0]), calibration)
    assert calm.monitor(samples)[1] is False
    score, alarm = shifted.monitor(samples)
    assert alarm and score > monitor.threshold
    with pytest.raises(SafeRaceError, match="--monitor spread"):
        ConformalStateSource(FeatureState(None), calibration).monitor(samples)
