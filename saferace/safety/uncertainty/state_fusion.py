"""A state source that fuses a perceived lane state with odometry in a Kalman filter.

A state network can be wrong and sure of it; the car's own sensors know better how its
heading changes: the yaw rate (IMU) less the map's curvature at the localised ``s`` times
the speed along the track. :class:`OdometryFusedStateSource` predicts ``[e_y, e_psi]`` with
that Frenet kinematics, takes the network's samples as a measurement with their covariance,
and leaves out a measurement whose Mahalanobis distance from the prediction is beyond a
chi-square gate. The filter gets the source's samples moved to the fused mean, so the chance
constraints keep the network's (calibrated) spread: a Kalman filter that took a network's
errors for independent ones would shrink it to a fraction of the real error. It cannot help
a network that is poor from its first frame (it then trusts its own dead reckoning); the
docs' learned-driver page gives the measurements.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from saferace.safety.uncertainty.state_sources import StateSource
from saferace.track.track import Track

#: 99% of a chi-square with 2 degrees of freedom: a measurement farther from the
#: prediction than this (in the innovation's own metric) is an outlier.
GATE_CHI2_2DOF_99 = 9.21


class OdometryFusedStateSource:
    """``[e_y, e_psi]`` from a Kalman filter over ``source``'s samples and odometry.

    Prediction over ``control_dt_s`` from the measured ``[v_x, v_y, r]`` (the mean of the
    last step's and this one's: a weaving car's yaw rate changes sign within a few steps):
    ``de_y/dt = v_x sin e_psi + v_y cos e_psi``, ``de_psi/dt = r - kappa(s) ds/dt`` with
    ``ds/dt = (v_x cos e_psi - v_y sin e_psi) / (1 - kappa e_y)`` and the map's curvature at
    ``info["s_m"]``; white process noise ``process_std`` (per sqrt(s)) covers slip and map
    error. Update: the mean and covariance of ``source``'s samples, ``min_measurement_std``
    added to the latter (MC-dropout samples can agree by chance), unless gated out. After
    ``max_gated_steps`` gated in a row the filter starts again from the measurement: a
    source that disagrees for that long is more likely right than odometry that drifted.
    Returned: ``source``'s samples moved to the posterior mean, their spread widened to the
    posterior's where that is wider, and their curvature. ``gated`` counts the measurements
    left out since the last reset.

    The gate catches a source that jumps away from the truth; one that drifts away over
    seconds moves the estimate with it (the gain on ``e_y`` is about 0.2 per step).
    """

    def __init__(
        self,
        source: StateSource,
        track: Track,
        control_dt_s: float,
        process_std: tuple[float, float] = (0.02, 0.02),
        min_measurement_std: tuple[float, float] = (0.03, 0.05),
        gate_chi2: float = GATE_CHI2_2DOF_99,
        max_gated_steps: int = 20,
    ) -> None:
        if control_dt_s <= 0.0 or gate_chi2 <= 0.0 or max_gated_steps < 1:
            raise ValueError(
                "need positive control_dt_s, gate_chi2 and max_gated_steps, got "
                f"{control_dt_s}, {gate_chi2}, {max_gated_steps}"
            )
        if min(process_std) <= 0.0 or min(min_measurement_std) <= 0.0:
            raise ValueError("process_std and min_measurement_std must be positive")
        self.source = source
        self.track = track
        self.control_dt_s = control_dt_s
        self.process_cov = np.diag(np.square(process_std)) * control_dt_s
        self.min_measurement_cov = np.diag(np.square(min_measurement_std))
        self.gate_chi2 = gate_chi2
        self.max_gated_steps = max_gated_steps
        self._mean: np.ndarray | None = None
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        self.source.reset(seed)
        self._mean = None
        self._cov = np.zeros((2, 2))
        self._velocity = np.zeros(3)
        self._gated_in_a_row = 0
        self.gated = 0

    def samples(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        perceived = np.atleast_2d(self.source.samples(observation, info))
        measured = perceived[:, :2].mean(axis=0)
        measured_cov = self.min_measurement_cov.copy()
        if len(perceived) > 1:
            measured_cov += np.cov(perceived[:, :2], rowvar=False)
        if self._mean is None or self._gated_in_a_row >= self.max_gated_steps:
            mean, cov = measured, measured_cov
            self._gated_in_a_row = 0
        else:
            kappa = self.track.centerline.curvature_scalar(float(info["s_m"]))
            velocity = 0.5 * (self._velocity + np.asarray(observation["velocity"], dtype=float))
            mean, jacobian = frenet_step(self._mean, velocity, kappa, self.control_dt_s)
            cov = jacobian @ self._cov @ jacobian.T + self.process_cov
            innovation = measured - mean
            innovation_cov = cov + measured_cov
            if innovation @ np.linalg.solve(innovation_cov, innovation) > self.gate_chi2:
                self.gated += 1
                self._gated_in_a_row += 1
            else:
                self._gated_in_a_row = 0
                gain = cov @ np.linalg.inv(innovation_cov)
                mean = mean + gain @ innovation
                cov = (np.eye(2) - gain) @ cov
                cov = 0.5 * (cov + cov.T)
        self._mean, self._cov = mean, cov
        self._velocity = np.asarray(observation["velocity"], dtype=float)
        deviations = perceived[:, :2] - measured
        spread = deviations.std(axis=0)
        widen = np.sqrt(np.diag(cov)) / np.where(spread > 0.0, spread, 1.0)
        deviations = deviations * np.where(spread > 0.0, np.maximum(widen, 1.0), 1.0)
        return np.column_stack([mean + deviations, perceived[:, 2]])

    def describe(self) -> dict:
        inner: dict[str, Any] = getattr(self.source, "describe", dict)()
        return {**inner, "fused_with_odometry": True, "gated_steps": self.gated}


def frenet_step(
    lane_state: np.ndarray, velocity: np.ndarray, kappa_radpm: float, dt_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """``[e_y, e_psi]`` after ``dt_s`` at body velocity ``[v_x, v_y, r]`` over a centre line of
    curvature ``kappa_radpm`` (one Euler step), and the step's Jacobian in ``[e_y, e_psi]``."""
    e_y, e_psi = lane_state
    v_x, v_y, yaw_rate = velocity
    sin, cos = math.sin(e_psi), math.cos(e_psi)
    stretch = max(1.0 - kappa_radpm * e_y, 1e-3)
    along = v_x * cos - v_y * sin
    across = v_x * sin + v_y * cos
    s_rate = along / stretch
    moved = np.array([e_y + dt_s * across, e_psi + dt_s * (yaw_rate - kappa_radpm * s_rate)])
    jacobian = np.eye(2) + dt_s * np.array(
        [
            [0.0, along],
            [-(kappa_radpm**2) * s_rate / stretch, kappa_radpm * across / stretch],
        ]
    )
    return moved, jacobian
