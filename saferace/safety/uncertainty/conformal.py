"""Calibrated intervals for an uncertain state: split conformal prediction and its online
variant.

Normalised split conformal prediction (Vovk et al.; Lei et al. 2018): on ``n`` frames no
network trained on, score each frame by ``max_i |error_i| / sigma_i`` over the outputs; the
``ceil((n + 1)(1 - alpha))``-th smallest score ``q`` makes ``mean +- q sigma`` cover every
output of a new exchangeable frame with probability at least ``1 - alpha``. Under a
distribution shift no such guarantee holds (Ovadia et al. 2019): :class:`AdaptiveConformal`
(Gibbs and Candes 2021) adapts the level online from the misses it is told of. The same
quantile rule fits an out-of-distribution score's threshold: on exchangeable frames it
raises on at most ``alpha`` of them: on the state network's spread
(:class:`SpreadMonitor`) or on its backbone features
(:class:`~saferace.safety.uncertainty.feature_monitor.FeatureMonitor`, which sees a new look).

Numpy only (no learning code), so that the filter's layer can hold and apply a calibration.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np
from scipy.stats import beta

from saferace.errors import ConfigError, SafeRaceError
from saferace.safety.uncertainty.feature_monitor import FeatureMonitor, feature_monitor

#: Floor of a frame's sigma in a score (an output that never varies has none).
MIN_SIGMA = 1e-9
#: Calibration scores a calibration keeps for online adaptation, at most.
MAX_STORED_SCORES = 1000


def conformal_quantile(scores: np.ndarray, alpha: float) -> float:
    """The ``ceil((n + 1)(1 - alpha))``-th smallest of ``n`` scores; ``inf`` when that rank
    exceeds ``n`` (too few frames for this ``alpha``: no finite threshold holds)."""
    if not 0.0 < alpha < 1.0:
        raise ConfigError("alpha", f"must be in (0, 1), got {alpha}")
    scores = np.sort(np.asarray(scores, dtype=float).ravel())
    if not len(scores):
        raise SafeRaceError("a conformal quantile needs at least one calibration score")
    rank = math.ceil((len(scores) + 1) * (1.0 - alpha))
    return float(scores[rank - 1]) if rank <= len(scores) else math.inf


def normalised_scores(mean: np.ndarray, sigma: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per frame, the largest error over the outputs in units of its sigma: ``(n,)``."""
    error = np.abs(np.asarray(mean, float) - np.asarray(truth, float))
    return np.max(error / np.maximum(np.asarray(sigma, float), MIN_SIGMA), axis=-1)


@dataclass(frozen=True)
class SpreadMonitor:
    """An out-of-distribution alarm on a frame's spread: the score ``max_i sigma_i /
    reference_i`` (``reference``: the calibration frames' median spread per output) raises
    above ``threshold``, the conformal quantile of the calibration frames' scores at
    ``alpha``, so on exchangeable frames it raises on at most ``alpha`` of them."""

    reference: tuple[float, ...]
    threshold: float
    alpha: float
    kind: str = "spread"

    def score(self, sigma: np.ndarray) -> float:
        ratio = np.asarray(sigma, float) / np.maximum(self.reference, MIN_SIGMA)
        return float(np.max(ratio))

    def raises(self, sigma: np.ndarray) -> tuple[float, bool]:
        """``(score, alarm)`` of one frame's spread."""
        score = self.score(sigma)
        return score, score > self.threshold

    def summary(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> SpreadMonitor:
        return cls(
            tuple(float(x) for x in values["reference"]),
            float(values["threshold"]),
            float(values["alpha"]),
        )


def fit_spread_monitor(sigma: np.ndarray, alpha: float = 0.05) -> SpreadMonitor:
    """The :class:`SpreadMonitor` of held-out frames' ``(n, outputs)`` spreads."""
    sigma = np.asarray(sigma, float)
    reference = tuple(float(x) for x in np.maximum(np.median(sigma, axis=0), MIN_SIGMA))
    scores = np.max(sigma / np.asarray(reference), axis=-1)
    return SpreadMonitor(reference, conformal_quantile(scores, alpha), alpha)


def fit_feature_monitor(features: np.ndarray, alpha: float = 0.05, seed: int = 0) -> FeatureMonitor:
    """The :class:`~saferace.safety.uncertainty.feature_monitor.FeatureMonitor` of held-out frames'
    ``(n, F)`` backbone features: its Gaussian fitted on a random half of them, its
    threshold the conformal quantile of the other half's scores."""
    features = np.asarray(features, float)
    half = np.random.default_rng(seed).permutation(len(features)) < len(features) // 2
    monitor = feature_monitor(features[half], alpha)
    return replace(monitor, threshold=conformal_quantile(monitor.scores(features[~half]), alpha))


#: An out-of-distribution monitor a calibration can hold.
Monitor = SpreadMonitor | FeatureMonitor
#: The monitors by their ``kind``.
MONITOR_KINDS: dict[str, type[SpreadMonitor] | type[FeatureMonitor]] = {
    "spread": SpreadMonitor,
    "features": FeatureMonitor,
}


@dataclass(frozen=True)
class ConformalCalibration:
    """``mean +- scale * sigma`` covers the truth with probability ``1 - alpha`` on frames
    exchangeable with the ``frames`` it was fitted on; ``monitor`` (if any) raises on frames
    unlike them. ``scores``: the calibration scores, sorted (at most
    :data:`MAX_STORED_SCORES`, evenly spaced in rank), for an online adaptation of the
    level (:class:`AdaptiveConformal`)."""

    alpha: float
    scale: float
    frames: int
    monitor: Monitor | None = None
    scores: tuple[float, ...] = ()

    def interval(self, mean: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        half = self.scale * np.asarray(sigma, float)
        return np.asarray(mean, float) - half, np.asarray(mean, float) + half

    def as_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> dict:
        """What a result row records: all but the scores and the monitor's arrays."""
        summary = {k: v for k, v in self.as_dict().items() if k not in ("scores", "monitor")}
        return {**summary, "monitor": None if self.monitor is None else self.monitor.summary()}

    @classmethod
    def from_dict(cls, values: dict) -> ConformalCalibration:
        monitor = values.get("monitor")
        return cls(
            float(values["alpha"]),
            float(values["scale"]),
            int(values["frames"]),
            None
            if monitor is None
            else MONITOR_KINDS[monitor.get("kind", "spread")].from_dict(monitor),
            tuple(float(x) for x in values.get("scores", ())),
        )


def stored_scores(scores: np.ndarray) -> tuple[float, ...]:
    """The scores a calibration keeps: sorted, at most :data:`MAX_STORED_SCORES` of them
    evenly spaced in rank."""
    ranks = np.linspace(0, len(scores) - 1, min(len(scores), MAX_STORED_SCORES))
    return tuple(float(x) for x in np.sort(scores)[np.round(ranks).astype(int)])


def calibrate(
    mean: np.ndarray,
    sigma: np.ndarray,
    truth: np.ndarray,
    alpha: float = 0.05,
    monitor_alpha: float | None = 0.05,
    features: np.ndarray | None = None,
) -> ConformalCalibration:
    """Fit the interval scale (and, with a ``monitor_alpha``, the monitor: on the frames'
    ``features`` where given, else on their spread) on held-out ``(n, outputs)`` predictions
    and truths."""
    scores = normalised_scores(mean, sigma, truth)
    monitor: Monitor | None = None
    if monitor_alpha is not None:
        monitor = (
            fit_spread_monitor(sigma, monitor_alpha)
            if features is None
            else fit_feature_monitor(features, monitor_alpha)
        )
    return ConformalCalibration(
        alpha, conformal_quantile(scores, alpha), len(scores), monitor, stored_scores(scores)
    )


def group_calibration(
    mean: np.ndarray,
    sigma: np.ndarray,
    truth: np.ndarray,
    groups: np.ndarray,
    alpha: float = 0.05,
    monitor: FeatureMonitor | None = None,
    features: np.ndarray | None = None,
) -> tuple[ConformalCalibration, list[dict]]:
    """A calibration that holds per group (a track), not only pooled over frames.

    Each group's own conformal quantile of its frames' scores is found, and the interval
    scale is the largest of the ``m`` groups': a new group exchangeable with them has its
    own quantile above all ``m`` with probability at most ``1 / (m + 1)``. So a track is
    covered at ``1 - alpha`` of its frames however its frames are spread over the lap,
    where a pooled quantile lets easy tracks pay for hard ones. The ``monitor`` (its
    Gaussian fitted elsewhere, e.g. on training frames) gets its threshold the same way,
    from ``features``. Also returns a row per group: its frames, quantiles, and the coverage
    and alarm rate it gets at the shared scale and threshold.
    """
    scores = normalised_scores(mean, sigma, truth)
    groups = np.asarray(groups)
    names = list(dict.fromkeys(groups.tolist()))
    if len(names) < 2:
        raise SafeRaceError(f"a calibration by groups needs at least 2 groups, got {len(names)}")
    if (monitor is None) != (features is None):
        raise SafeRaceError("a monitor's threshold by groups needs the frames' features")
    monitor_scores = None if monitor is None else monitor.scores(np.asarray(features, float))
    scales = {name: conformal_quantile(scores[groups == name], alpha) for name in names}
    thresholds = (
        {}
        if monitor_scores is None
        else {name: conformal_quantile(monitor_scores[groups == name], alpha) for name in names}
    )
    scale = max(scales.values())
    if monitor is not None:
        monitor = replace(monitor, threshold=max(thresholds.values()))
    rows = []
    for name in names:
        mine = groups == name
        row = {
            "group": name,
            "frames": int(mine.sum()),
            "own scale": scales[name],
            "coverage": float(np.mean(scores[mine] <= scale)),
        }
        if monitor_scores is not None and monitor is not None:
            row["own threshold"] = thresholds[name]
            row["alarm rate"] = float(np.mean(monitor_scores[mine] > monitor.threshold))
        rows.append(row)
    return ConformalCalibration(alpha, scale, len(scores), monitor, stored_scores(scores)), rows


def coverage(
    lower: np.ndarray, upper: np.ndarray, truth: np.ndarray
) -> tuple[float, tuple[float, float]]:
    """The share of frames whose every output lies inside its interval, and its
    Clopper-Pearson 95% band."""
    inside = np.all((np.asarray(truth) >= lower) & (np.asarray(truth) <= upper), axis=-1)
    return float(inside.mean()), clopper_pearson(int(inside.sum()), len(inside))


def clopper_pearson(successes: int, trials: int, level: float = 0.95) -> tuple[float, float]:
    """The exact (Clopper-Pearson) confidence band of a binomial proportion."""
    tail = 0.5 * (1.0 - level)
    low = 0.0 if successes == 0 else float(beta.ppf(tail, successes, trials - successes + 1))
    high = (
        1.0 if successes == trials else float(beta.ppf(1 - tail, successes + 1, trials - successes))
    )
    return low, high


class AdaptiveConformal:
    """Adaptive conformal inference (Gibbs and Candes 2021): the level moves with the misses,
    ``alpha_{t+1} = alpha_t + gamma (alpha - miss_t)``, and the interval scale is the
    calibration scores' quantile at that level. Over any sequence, shifted or not, the long-run
    miss rate stays within ``(max(alpha_1, 1 - alpha_1) + gamma) / (gamma T)`` of ``alpha``.

    Who says whether a step missed matters: lagged ground truth is *oracle feedback* (a
    simulator has it, a real car does not); :meth:`update` takes either and the caller
    names which in what it reports.
    """

    def __init__(self, scores: np.ndarray, alpha: float = 0.05, gamma: float = 0.005) -> None:
        if gamma <= 0.0:
            raise SafeRaceError(f"gamma must be positive, got {gamma}")
        self.scores = np.sort(np.asarray(scores, float).ravel())
        self.target = alpha
        self.gamma = gamma
        self.alpha_t = alpha

    @property
    def scale(self) -> float:
        """The interval scale at the current level (``inf`` at a level of 0 or below)."""
        if self.alpha_t <= 0.0:
            return math.inf
        if self.alpha_t >= 1.0:
            return 0.0
        return conformal_quantile(self.scores, self.alpha_t)

    def update(self, missed: bool) -> None:
        """One step's feedback: whether the interval used missed the truth."""
        self.alpha_t += self.gamma * (self.target - float(missed))
