"""Where the safety filter gets the car's lane state: ground truth, noisy truth, or a network.

A state source returns ``n`` samples of ``[e_y_m, e_psi_rad, kappa_radpm]`` (lateral offset
from the centerline, heading error, centerline curvature), the part of the state that a
camera must perceive. The filter combines them with the measured velocities
``[v_x, v_y, r]`` of the observation (IMU and wheel encoders). The learned state network
(paper Sec. 3.4, MC dropout) implements :class:`StateSource` by returning its dropout
samples.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

LANE_STATE_NAMES = ("e_y_m", "e_psi_rad", "kappa_radpm")


class StateSource(Protocol):
    """Anything that turns an observation (and, for oracles, ``info``) into state samples."""

    def reset(self, seed: int | None = None) -> None: ...

    def samples(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        """``(n, 3)`` samples of ``[e_y_m, e_psi_rad, kappa_radpm]``."""
        ...


def prefetch(source: StateSource, observation: dict[str, np.ndarray]) -> None:
    """Let the source under ``source`` (through its wrappers' ``source``) that can start on
    an observation early (a learned one: ``prefetch``) start on ``observation`` now."""
    current: Any = source
    while current is not None and not hasattr(current, "prefetch"):
        current = getattr(current, "source", None)
    if current is not None:
        current.prefetch(observation)


def true_lane_state(info: dict[str, Any]) -> np.ndarray:
    """The simulator's ``[e_y, e_psi, kappa]`` from ``info``."""
    return np.array([info[name] for name in LANE_STATE_NAMES], dtype=float)


def reads_image(source: StateSource) -> bool:
    """Whether ``source`` (or the source it wraps, its ``source``) reads the camera's frame,
    as a network does, rather than the simulator's state, as the oracles do (their
    ``reads_image`` is False): a stale frame is no measurement only for one that reads it."""
    inner = getattr(source, "source", None)
    if inner is not None:
        return reads_image(inner)
    return bool(getattr(source, "reads_image", True))


class OracleStateSource:
    """The simulator's ground truth: one exact sample."""

    reads_image = False

    def reset(self, seed: int | None = None) -> None:
        """Nothing to reset: the truth has no state."""

    def samples(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        return true_lane_state(info)[None, :]


class NoisyOracleStateSource:
    """``n`` samples around the truth, as a calibrated uncertain estimator would give them.

    Each step the estimate is off the truth by ``N(0, std)`` and its ``n`` samples spread by
    ``N(0, std)`` around the estimate: the samples' spread matches the estimate's real error,
    so the truth looks like one more sample. (Samples centred on the truth would make their
    mean almost exact, and no filter would need the spread.)
    """

    reads_image = False

    def __init__(
        self,
        std: tuple[float, float, float] = (0.05, 0.05, 0.0),
        n_samples: int = 20,
        seed: int | None = None,
    ) -> None:
        if n_samples < 2:
            raise ValueError(f"a noisy oracle needs at least 2 samples, got {n_samples}")
        if len(std) != 3 or min(std) < 0.0:
            raise ValueError(f"std must be 3 non-negative numbers (e_y, e_psi, kappa), got {std}")
        self.std = np.asarray(std, dtype=float)
        self.n_samples = n_samples
        self._seed = seed
        self._rng = np.random.default_rng(seed)

    def reset(self, seed: int | None = None) -> None:
        self._rng = np.random.default_rng(self._seed if seed is None else seed)

    def samples(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        estimate = true_lane_state(info) + self._rng.standard_normal(3) * self.std
        return estimate + self._rng.standard_normal((self.n_samples, 3)) * self.std


class SpreadScaledStateSource:
    """Another source's samples with their spread about the mean scaled per component.

    An MC-dropout spread that is several times smaller than the network's real error makes
    the chance constraints tighten too little; scaling it by a factor fitted on frames the
    network never trained on (variance scaling, Laves et al. 2020; see
    :mod:`saferace.learning.calibration`) makes the spread match the error on average.
    """

    def __init__(self, source: StateSource, scale: tuple[float, float, float]) -> None:
        if len(scale) != 3 or min(scale) <= 0.0:
            raise ValueError(f"scale must be 3 positive numbers (e_y, e_psi, kappa), got {scale}")
        self.source = source
        self.scale = np.asarray(scale, dtype=float)

    def reset(self, seed: int | None = None) -> None:
        self.source.reset(seed)

    def samples(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        samples = self.source.samples(observation, info)
        mean = samples.mean(axis=0)
        return mean + (samples - mean) * self.scale

    def describe(self) -> dict:
        inner: dict[str, Any] = getattr(self.source, "describe", dict)()
        return {**inner, "spread_scale": self.scale.tolist()}
