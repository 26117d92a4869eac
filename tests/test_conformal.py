"""Split conformal prediction, the monitor's threshold and adaptive conformal inference on
synthetic data whose answers are known: each test fails if the rule it names is off by one
rank or one sign."""

from __future__ import annotations

import math

import numpy as np
import pytest

from saferace.errors import SafeRaceError
from saferace.safety.uncertainty.conformal import (
    MAX_STORED_SCORES,
    AdaptiveConformal,
    ConformalCalibration,
    calibrate,
    clopper_pearson,
    conformal_quantile,
    coverage,
    fit_spread_monitor,
    normalised_scores,
)

ALPHA = 0.05
N_CALIBRATION = 100  # the 96th of 100 scores: ceil(101 * 0.95); ceil(100 * 0.95) is 95


def heteroscedastic(rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    """Predictions of 3 outputs whose errors are heavy-tailed multiples of their sigma."""
    sigma = rng.uniform(0.01, 0.3, (n, 3))
    truth = rng.normal(0.0, 1.0, (n, 3))
    mean = truth + sigma * rng.standard_t(4, (n, 3))
    return mean, sigma, truth


def test_split_conformal_covers_within_its_bounds_over_many_trials():
    """Marginal coverage lies in [1 - alpha, 1 - alpha + 1/(n + 1)] (Lei et al. 2018)."""
    rng = np.random.default_rng(0)
    trials, tests = 400, 500
    covered = []
    for _ in range(trials):
        calibration = calibrate(*heteroscedastic(rng, N_CALIBRATION), alpha=ALPHA)
        mean, sigma, truth = heteroscedastic(rng, tests)
        covered.append(coverage(*calibration.interval(mean, sigma), truth)[0])
    mean_coverage = float(np.mean(covered))
    spread = np.std(covered) / math.sqrt(trials)
    assert (
        1 - ALPHA - 4 * spread <= mean_coverage <= 1 - ALPHA + 1 / (N_CALIBRATION + 1) + 4 * spread
    )
    # a quantile one rank lower (without the + 1) covers 95/101 on average, 4 spreads below
    assert 4 * spread < 0.01


def test_the_quantile_is_the_ceil_rank_and_infinite_when_too_few():
    scores = np.arange(1.0, 101.0)  # 1..100
    assert conformal_quantile(scores, 0.05) == 96.0
    assert conformal_quantile(scores[:10], 0.05) == math.inf  # rank 11 of 10
    with pytest.raises(ValueError, match="alpha"):
        conformal_quantile(scores, 1.5)
    assert conformal_quantile(scores[:19], 0.05) == 19.0  # rank 19 of 19: the largest
    for edge in (0.0, 1.0):
        with pytest.raises(ValueError, match="alpha"):
            conformal_quantile(scores, edge)


def test_coverage_counts_the_interval_closed_and_its_band_is_the_exact_one():
    from scipy.stats import binomtest

    truth = np.array([[0.0, 1.0], [1.0, 0.5], [2.0, 0.5], [0.5, 0.5]])
    lower, upper = np.zeros(2), np.ones(2)
    share, band = coverage(lower, upper, truth)
    assert share == 0.75  # the ends belong to the interval; 2.0 lies outside
    assert band == clopper_pearson(3, 4)
    for successes, trials in ((3, 4), (0, 7), (7, 7), (37, 40)):
        exact = binomtest(successes, trials).proportion_ci(0.95, method="exact")
        expected = (exact.low, exact.high)
        assert clopper_pearson(successes, trials) == pytest.approx(expected, abs=1e-9)
    exact = binomtest(37, 40).proportion_ci(0.9, method="exact")
    assert clopper_pearson(37, 40, 0.9) == pytest.approx((exact.low, exact.high), abs=1e-9)


def test_a_calibration_keeps_its_extreme_scores_and_evenly_spaced_ranks():
    rng = np.random.default_rng(4)
    for frames in (30, 2500):
        calibration = calibrate(*heteroscedastic(rng, frames), alpha=ALPHA, monitor_alpha=None)
        kept = np.array(calibration.scores)
        assert len(kept) == min(frames, MAX_STORED_SCORES) and np.all(np.diff(kept) >= 0)
    mean, sigma, truth = heteroscedastic(np.random.default_rng(5), 2500)
    scores = np.sort(normalised_scores(mean, sigma, truth))
    kept = np.array(calibrate(mean, sigma, truth, ALPHA, None).scores)
    assert kept[0] == scores[0] and kept[-1] == scores[-1]
    assert kept[MAX_STORED_SCORES // 2] == pytest.approx(np.median(scores), rel=0.02)


def test_normalised_scores_take_the_worst_output():
    mean, sigma, truth = np.array([[1.0, 0.0]]), np.array([[0.5, 0.1]]), np.array([[0.0, 0.3]])
    assert normalised_scores(mean, sigma, truth) == pytest.approx([3.0])


def test_a_monitor_threshold_raises_on_at_most_alpha_of_exchangeable_frames():
    rng = np.random.default_rng(1)
    rates = []
    for _ in range(300):
        threshold = conformal_quantile(rng.gamma(2.0, 1.0, 199), ALPHA)
        rates.append(np.mean(rng.gamma(2.0, 1.0, 400) > threshold))
    spread = np.std(rates) / math.sqrt(len(rates))
    assert np.mean(rates) <= ALPHA + 3 * spread
    assert np.mean(rates) >= ALPHA - 1 / 200 - 3 * spread  # and not needlessly quiet


def test_the_spread_monitor_raises_on_alpha_of_like_frames_and_on_a_grown_spread():
    rng = np.random.default_rng(3)

    def spreads(n: int) -> np.ndarray:
        return rng.lognormal(np.log([0.02, 0.01]), 0.3, (n, 2))

    rates, grown_rates = [], []
    for _ in range(100):
        monitor = fit_spread_monitor(spreads(199), ALPHA)
        like = spreads(400)
        rates.append(np.mean([monitor.raises(sigma)[1] for sigma in like]))
        like[:, 1] *= 3.0  # one output's spread tripled: the network is in doubt
        grown_rates.append(np.mean([monitor.raises(sigma)[1] for sigma in like]))
    spread = np.std(rates) / math.sqrt(len(rates))
    assert ALPHA - 1 / 200 - 3 * spread <= np.mean(rates) <= ALPHA + 3 * spread
    assert np.mean(grown_rates) > 0.9
    monitor = fit_spread_monitor(np.array([[1.0, 4.0], [2.0, 2.0], [3.0, 1.0]]), 0.5)
    assert monitor.reference == (2.0, 2.0)  # the median spread of each output
    assert monitor.raises(np.array([1.0, 5.0])) == (2.5, monitor.threshold < 2.5)
    at_threshold = np.array(monitor.reference) * monitor.threshold
    assert monitor.raises(at_threshold) == (pytest.approx(monitor.threshold), False)  # above it


def test_adaptive_conformal_edges_of_the_level():
    scores = np.arange(1.0, 101.0)
    with pytest.raises(SafeRaceError, match="gamma"):
        AdaptiveConformal(scores, ALPHA, 0.0)
    adaptive = AdaptiveConformal(scores, ALPHA, 0.01)
    assert adaptive.scale == 96.0
    for level, scale in ((0.0, math.inf), (-0.1, math.inf), (1.0, 0.0), (1.5, 0.0)):
        adaptive.alpha_t = level
        assert adaptive.scale == scale, level
    adaptive.alpha_t = ALPHA
    adaptive.update(missed=True)  # a miss lowers the level, widening the interval
    assert adaptive.alpha_t == pytest.approx(ALPHA + 0.01 * (ALPHA - 1.0))
    adaptive.update(missed=False)
    assert adaptive.alpha_t == pytest.approx(ALPHA + 0.01 * (2 * ALPHA - 1.0))


def test_adaptive_conformal_keeps_the_long_run_miss_rate_under_a_shift():
    rng = np.random.default_rng(2)
    calibration_scores = np.abs(rng.standard_normal(500))
    steps, gamma = 4000, 0.01
    shift = np.where(np.arange(steps) < steps // 2, 1.0, 3.0)  # the errors triple halfway
    adaptive = AdaptiveConformal(calibration_scores, ALPHA, gamma)
    fixed_scale = adaptive.scale
    adaptive_misses, fixed_misses = [], []
    for t in range(steps):
        score = abs(rng.standard_normal()) * shift[t]
        missed = score > adaptive.scale
        adaptive_misses.append(missed)
        fixed_misses.append(score > fixed_scale)
        adaptive.update(missed)  # lagged truth: oracle feedback
    bound = (max(ALPHA, 1 - ALPHA) + gamma) / (gamma * steps)
    assert abs(np.mean(adaptive_misses) - ALPHA) <= bound
    assert np.mean(fixed_misses) > ALPHA + 3 * bound  # without adapting it misses far more


def test_a_calibration_survives_a_round_trip_and_widens_the_interval():
    calibration = ConformalCalibration(alpha=0.05, scale=2.5, frames=120)
    assert ConformalCalibration.from_dict(calibration.as_dict()) == calibration
    lower, upper = calibration.interval(np.array([0.1, 0.0]), np.array([0.02, 0.1]))
    assert lower == pytest.approx([0.05, -0.25]) and upper == pytest.approx([0.15, 0.25])


def test_clopper_pearson_brackets_the_proportion():
    low, high = clopper_pearson(95, 100)
    assert 0.88 < low < 0.95 < high < 0.99
    assert clopper_pearson(0, 10)[0] == 0.0 and clopper_pearson(10, 10)[1] == 1.0
