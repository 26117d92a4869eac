"""Intervals of the perceived state: from a conformal calibration or the samples' spread,
and the points a robust filter checks."""

from __future__ import annotations

import numpy as np
import pytest

from saferace.safety.conformal import ConformalCalibration
from saferace.safety.intervals import (
    ConformalStateSource,
    interval_points,
    state_interval,
)
from saferace.safety.state_sources import NoisyOracleStateSource, OracleStateSource

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
