"""Intervals of the perceived state: from a conformal calibration or the samples' spread,
and the points a robust filter checks."""

from __future__ import annotations

import numpy as np
import pytest

from saferace.safety.uncertainty.conformal import ConformalCalibration
from saferace.safety.uncertainty.intervals import (
    ConformalStateSource,
    interval_points,
    state_interval,
)
from saferace.safety.uncertainty.state_sources import NoisyOracleStateSource, OracleStateSource

INFO = {"e_y_m": 0.1, "e_psi_rad": -0.05, "kappa_radpm": 0.5}


def test_a_conformal_source_widens_its_samples_spread_by_the_calibrated_scale():
    source = ConformalStateSource(
        NoisyOracleStateSource((0.05, 0.05, 0.0), 50, seed=0), ConformalCalibration(0.05, 3.0, 99)
    )
    samples = source.samples({}, INFO)
    lower, upper = state_interval(source, samples, z=1.0)
    mean, std = samples.mean(axis=0), samples.std(axis=0)
    np.testing.assert_allclose(upper - mean, 3.0 * std)
    np.testing.assert_allclose(mean - lower, 3.0 * std)
    assert source.describe()["conformal"]["scale"] == 3.0


def test_a_source_without_a_calibration_gets_z_spreads_and_the_truth_a_point():
    samples = np.array([[0.0, 0.0, 1.0], [0.2, 0.1, 1.0]])
    lower, upper = state_interval(NoisyOracleStateSource(), samples, z=2.0)
    np.testing.assert_allclose(lower, [-0.1, -0.05, 1.0])
    np.testing.assert_allclose(upper, [0.3, 0.15, 1.0])
    truth = OracleStateSource().samples({}, INFO)
    lower, upper = state_interval(OracleStateSource(), truth, z=2.0)
    assert np.array_equal(lower, upper)
    assert interval_points(lower, upper).shape == (1, 3)


@pytest.mark.parametrize(("degenerate", "count"), [(0, 9), (1, 5), (2, 3)])
def test_interval_points_are_the_corners_and_the_centre(degenerate: int, count: int):
    lower = np.array([-0.1, -0.2, 0.5])
    upper = lower + np.array([0.2, 0.4, 0.1])
    upper[3 - degenerate :] = lower[3 - degenerate :]
    points = interval_points(lower, upper)
    assert len(points) == count
    assert np.all(points >= lower) and np.all(points <= upper)
    np.testing.assert_allclose(points.min(axis=0), lower)
    np.testing.assert_allclose(points.max(axis=0), upper)
    np.testing.assert_allclose(points[-1], 0.5 * (lower + upper))


class FixedSamples:
    """The same samples every step, and the features a network saw (``None``: none)."""

    def __init__(self, samples: np.ndarray, features: np.ndarray | None = None) -> None:
        self._samples, self.last_features = samples, features

    def reset(self, seed: int | None = None) -> None:
        """Nothing to reset."""

    def samples(self, observation: dict, info: dict) -> np.ndarray:
        return self._samples


def test_a_conformal_source_asks_its_calibrations_own_monitor():
    from saferace.errors import SafeRaceError
    from saferace.safety.uncertainty.conformal import SpreadMonitor, fit_feature_monitor

    narrow = np.array([[0.0, 0.0, 0.5], [0.02, 0.01, 0.5]])  # spreads 0.01, 0.005
    wide = np.array([[0.0, 0.0, 0.5], [0.2, 0.01, 0.5]])  # the offset's spread ten times
    spread = SpreadMonitor(reference=(0.01, 0.005), threshold=2.0, alpha=0.05)
    for samples, alarm in ((narrow, False), (wide, True)):
        source = ConformalStateSource(
            FixedSamples(samples), ConformalCalibration(0.05, 3.0, 99, spread)
        )
        score, raised = source.monitor(source.samples({}, INFO))
        assert raised is alarm and score == pytest.approx(1.0 if not alarm else 10.0)
    unmonitored = ConformalStateSource(FixedSamples(wide), ConformalCalibration(0.05, 3.0, 99))
    assert unmonitored.monitor(wide) == (None, False)

    rng = np.random.default_rng(0)
    features = fit_feature_monitor(rng.normal(0.0, 1.0, (200, 8)), 0.05)
    calibration = ConformalCalibration(0.05, 3.0, 99, features)
    for seen, alarm in ((np.zeros(8), False), (np.full(8, 10.0), True)):
        source = ConformalStateSource(FixedSamples(narrow, seen), calibration)
        assert source.monitor(narrow) == features.raises(seen)
        assert source.monitor(narrow)[1] is alarm
    blind = ConformalStateSource(OracleStateSource(), calibration)
    with pytest.raises(SafeRaceError, match="--monitor spread"):
        blind.monitor(narrow)
