"""Adaptive conformal intervals for the perceived state, with two kinds of feedback.

:class:`AdaptiveConformalStateSource` widens or narrows a conformally calibrated source's
interval online (Gibbs and Candes 2021, :class:`~saferace.safety.uncertainty.conformal.
AdaptiveConformal`): after each step it learns whether the interval missed, and the level
moves by ``gamma (alpha - miss)``. Who says it missed decides whether a real car could use
it:

- ``oracle``: the simulator's truth, one control step late. A benchmark's upper bound:
  **oracle feedback**, which no real car has.
- ``odometry``: no truth. The last interval's centre is carried one step forward with the
  car's own odometry (yaw rate, speed, the map's curvature at the localised ``s``: the
  Frenet kinematics of :mod:`saferace.safety.uncertainty.state_fusion`); the interval missed if that
  prediction of ``[e_y, e_psi]`` falls outside the new one. It flags estimates that jump
  further than their interval allows; a network wrong in the same way for many frames in a
  row passes it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from saferace.names import ADAPTIVE_FEEDBACK as FEEDBACK_KINDS
from saferace.safety.uncertainty.conformal import AdaptiveConformal
from saferace.safety.uncertainty.intervals import ConformalStateSource
from saferace.safety.uncertainty.state_sources import true_lane_state
from saferace.track.track import Track

#: The step of the level's update: at 20 Hz, a miss rate off by 0.5 moves the level by 0.1
#: in a second.
ACI_GAMMA = 0.01


class AdaptiveConformalStateSource:
    """A conformally calibrated source whose interval scale adapts online (see the module)."""

    def __init__(
        self,
        source: ConformalStateSource,
        feedback: str,
        track: Track,
        control_dt_s: float,
        gamma: float = ACI_GAMMA,
    ) -> None:
        if feedback not in FEEDBACK_KINDS:
            raise ValueError(f"feedback must be one of {FEEDBACK_KINDS}, got {feedback!r}")
        if not source.calibration.scores:
            raise ValueError(
                "the calibration keeps no scores to adapt over: calibrate the checkpoint again "
                "with saferace calibrate"
            )
        self.source = source
        self.feedback = feedback
        self.track = track
        self.control_dt_s = control_dt_s
        self.gamma = gamma
        self.misses = self.steps = 0
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        self.source.reset(seed)
        calibration = self.source.calibration
        self.adaptive = AdaptiveConformal(
            np.asarray(calibration.scores), calibration.alpha, self.gamma
        )
        #: The interval last given out (the one a filter used), and that step's truth
        #: (oracle feedback) and measured velocities.
        self._given: tuple[np.ndarray, np.ndarray] | None = None
        self._step: tuple[np.ndarray, np.ndarray] | None = None

    def samples(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        """This step's samples, after learning whether the last interval given out missed."""
        samples = self.source.samples(observation, info)
        if self._given is not None and self._step is not None:
            missed = self._missed(samples, observation, info)
            self.adaptive.update(missed)
            self.misses += missed
            self.steps += 1
        self._given = None
        truth = true_lane_state(info) if self.feedback == "oracle" else np.full(3, np.nan)
        self._step = truth, np.asarray(observation["velocity"], float)
        return samples

    def interval(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``mean +- scale std`` at the current level (unbounded at a level of 0 or below,
        where no quantile is finite: the filter then falls back to a stop); remembered as
        the interval the next step's feedback judges."""
        lower, upper = self._interval(samples)
        self._given = lower, upper
        return lower, upper

    def monitor(self, samples: np.ndarray) -> tuple[float | None, bool]:
        return self.source.monitor(samples)

    def describe(self) -> dict:
        return {
            **self.source.describe(),
            "adaptive": {
                "feedback": self.feedback,
                "oracle_feedback": self.feedback == "oracle",
                "gamma": self.gamma,
            },
        }

    def _interval(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        scale = self.adaptive.scale
        if math.isinf(scale):  # the level asks for everything: no state can be ruled out
            return np.full(3, -math.inf), np.full(3, math.inf)
        mean, std = samples.mean(axis=0), samples.std(axis=0)
        return mean - scale * std, mean + scale * std

    def _missed(
        self, samples: np.ndarray, observation: dict[str, np.ndarray], info: dict[str, Any]
    ) -> bool:
        """Whether the last interval given out missed: the truth it should have held
        (oracle), or the odometry's prediction of this step's state from its centre, which
        this step's interval at the same level should hold (odometry)."""
        assert self._given is not None and self._step is not None
        (last_lower, last_upper), (truth, velocity) = self._given, self._step
        if self.feedback == "oracle":
            lane = slice(0, 2)  # what the calibration covers
            return bool(np.any((truth[lane] < last_lower[lane]) | (truth[lane] > last_upper[lane])))
        if not np.all(np.isfinite(last_lower[:2])):
            return False  # an unbounded interval holds any state
        predicted = self._predicted(0.5 * (last_lower + last_upper), velocity, observation, info)
        lower, upper = self._interval(samples)
        return bool(np.any((predicted < lower[:2]) | (predicted > upper[:2])))

    def _predicted(
        self,
        centre: np.ndarray,
        previous_velocity: np.ndarray,
        observation: dict[str, np.ndarray],
        info: dict[str, Any],
    ) -> np.ndarray:
        """``[e_y, e_psi]`` carried from ``centre`` over one step by the Frenet kinematics
        at the mean of the last step's and this one's measured velocities."""
        v_x, v_y, yaw_rate = 0.5 * (previous_velocity + np.asarray(observation["velocity"]))
        e_y, e_psi = float(centre[0]), float(centre[1])
        kappa = self.track.centerline.curvature_scalar(float(info["s_m"]))
        s_rate = (v_x * math.cos(e_psi) - v_y * math.sin(e_psi)) / (1.0 - kappa * e_y)
        return np.array(
            [
                e_y + self.control_dt_s * (v_x * math.sin(e_psi) + v_y * math.cos(e_psi)),
                e_psi + self.control_dt_s * (yaw_rate - kappa * s_rate),
            ]
        )
