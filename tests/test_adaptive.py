"""Adaptive conformal intervals of the perceived state: oracle and odometry feedback."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from saferace.safety.uncertainty.adaptive import ACI_GAMMA, AdaptiveConformalStateSource
from saferace.safety.uncertainty.conformal import ConformalCalibration, calibrate
from saferace.safety.uncertainty.intervals import ConformalStateSource, state_interval
from saferace.track import Track
from tests.test_dead_reckoning import lane_state_on_circle, on_circle

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


def moved_round_the_circle(
    lane_state: tuple[float, float], before: np.ndarray, after: np.ndarray, dt_s: float
) -> np.ndarray:
    """``[e_y, e_psi]`` after ``dt_s`` on the 2 m circle of ``tests/test_dead_reckoning.py``,
    the body's velocities ``[v_x, v_y, yaw rate]`` changing evenly from ``before`` to
    ``after``: its motion integrated finely, then read back by polar geometry."""
    centre = on_circle(0.0)
    x, y = centre[:2] + lane_state[0] * np.array([-np.sin(centre[2]), np.cos(centre[2])])
    yaw = centre[2] + lane_state[1]
    substeps = 5000
    h = dt_s / substeps
    for k in range(substeps):
        v_x, v_y, yaw_rate = before + (after - before) * (k + 0.5) / substeps
        x += h * (v_x * np.cos(yaw) - v_y * np.sin(yaw))
        y += h * (v_x * np.sin(yaw) + v_y * np.cos(yaw))
        yaw += h * yaw_rate
    e_y, e_psi, _ = lane_state_on_circle(np.array([x, y, yaw]))
    return np.array([e_y, e_psi])


def test_odometry_feedback_carries_the_last_centre_where_the_car_goes_in_a_bend():
    """On a 2 m circle (curvature 0.5) the last interval's centre, 0.3 m inside at 0.2 rad,
    is carried over the 50 ms step as the car speeds up from ``[3, 0.1, 1.0]`` to ``[3.4,
    0.1, 1.4]``: to within a first-order step's error (3 mm, 2 mrad) of where the car goes,
    which moved 34 mm and -33 mrad (read at the step's end velocities alone, 5.5 mrad
    off). An interval of +-5 mm and +-5 mrad round where the car went is not missed; the
    same round where it was, as a network that lags a frame gives, is."""
    circle = SimpleNamespace(centerline=SimpleNamespace(curvature_scalar=lambda s_m: 0.5))
    before, after, dt_s = np.array([3.0, 0.1, 1.0]), np.array([3.4, 0.1, 1.4]), 0.05
    last = np.array([0.3, 0.2, 0.0])
    moved = moved_round_the_circle((0.3, 0.2), before, after, dt_s)
    misses = {}
    for name, second in (("where it went", [*moved, 0.0]), ("where it was", last)):
        estimates = np.array([last, second])
        source = AdaptiveConformalStateSource(
            calibrated(Scripted(estimates), np.random.default_rng(2)), "odometry", circle, dt_s
        )
        source.source.source.std = 0.005 / source.adaptive.scale  # +-5 mm and 5 mrad
        predicted = source._predicted(last, before, {"velocity": after}, {"s_m": 1.0})
        assert np.all(np.abs(predicted - moved) < [3e-3, 2e-3]), predicted - moved
        for velocity in (before, after):
            source.interval(source.samples({"velocity": velocity}, {"s_m": 1.0}))
        misses[name] = source.misses
    assert misses == {"where it went": 0, "where it was": 1}
