"""An out-of-distribution alarm on what the state network sees: its backbone features.

A network's spread measures what it knows it does not know; under a new look (light,
textures, camera pose, blur) an MC-dropout spread hardly moved while the error grew tenfold,
so a monitor on the spread stays quiet exactly when it is needed. The backbone's features
move with the look. Following Lee et al. 2018 ("A simple unified framework for detecting
out-of-distribution samples"), the score of a frame is its Mahalanobis distance from frames
the network is known to work on, here in the leading principal subspace of their features
plus the residual outside it (probabilistic PCA: a full 512-dimensional covariance cannot be
estimated from a few hundred frames):

``score = sum_j (c_j . (f - mu))^2 / var_j + |residual|^2 / residual_var``

The Gaussian is fitted on one part of the held-out frames and the threshold on the other:
the conformal quantile of their scores at ``alpha``, so that on frames exchangeable with
them the monitor raises on at most ``alpha`` of them.

Numpy only, so that the filter's layer can hold and apply it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from saferace.errors import SafeRaceError

#: Principal directions of the features kept, at most.
FEATURE_COMPONENTS = 16
#: Floor of a direction's (and the residual's) variance.
MIN_VARIANCE = 1e-9


@dataclass(frozen=True)
class FeatureMonitor:
    """Raises on frames whose backbone features lie far from the fitted frames'
    (``score > threshold``). ``mean`` ``(F,)``, ``components`` ``(k, F)`` orthonormal rows,
    ``variances`` ``(k,)``, ``residual_variance``: the per-frame mean squared norm of the
    fitted frames' features outside the components."""

    mean: tuple[float, ...]
    components: tuple[tuple[float, ...], ...]
    variances: tuple[float, ...]
    residual_variance: float
    threshold: float
    alpha: float
    kind: str = "features"

    def scores(self, features: np.ndarray) -> np.ndarray:
        """The score of each of ``(n, F)`` frames' features."""
        features = np.atleast_2d(np.asarray(features, float))
        if features.shape[1] != len(self.mean):
            raise SafeRaceError(
                f"the feature monitor was fitted on {len(self.mean)} features, got "
                f"{features.shape[1]} (a checkpoint's monitor belongs to its own network)"
            )
        mean, components, variances = self._arrays
        centred = features - mean
        projected = centred @ components.T
        residual = centred - projected @ components
        return np.sum(projected**2 / variances, axis=1) + np.sum(residual**2, axis=1) / max(
            self.residual_variance, MIN_VARIANCE
        )

    @cached_property
    def _arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The mean, components and variances as arrays, made once (they are scored every
        step; the fields stay tuples, for the checkpoint's metadata)."""
        return np.asarray(self.mean), np.asarray(self.components), np.asarray(self.variances)

    def raises(self, features: np.ndarray) -> tuple[float, bool]:
        """``(score, alarm)`` of one frame's features."""
        score = float(self.scores(features)[0])
        return score, score > self.threshold

    def summary(self) -> dict:
        """What a result row records: the kind, the size and the threshold."""
        return {
            "kind": self.kind,
            "features": len(self.mean),
            "components": len(self.components),
            "threshold": self.threshold,
            "alpha": self.alpha,
        }

    @classmethod
    def from_dict(cls, values: dict) -> FeatureMonitor:
        return cls(
            tuple(float(x) for x in values["mean"]),
            tuple(tuple(float(x) for x in row) for row in values["components"]),
            tuple(float(x) for x in values["variances"]),
            float(values["residual_variance"]),
            float(values["threshold"]),
            float(values["alpha"]),
        )


def feature_monitor(
    features: np.ndarray, alpha: float, components: int = FEATURE_COMPONENTS
) -> FeatureMonitor:
    """The monitor of the Gaussian fitted on ``(n, F)`` ``features``, its threshold not yet
    set (``inf``: see :func:`saferace.safety.uncertainty.conformal.fit_feature_monitor`)."""
    features = np.asarray(features, float)
    if len(features) < 3:
        raise SafeRaceError(
            f"a feature monitor needs at least 3 frames to fit on, got {len(features)}"
        )
    mean = features.mean(axis=0)
    centred = features - mean
    _, singular, directions = np.linalg.svd(centred, full_matrices=False)
    kept = min(components, len(features) - 1, features.shape[1] - 1)
    variances = np.maximum(singular[:kept] ** 2 / (len(features) - 1), MIN_VARIANCE)
    basis = directions[:kept]
    residual = centred - centred @ basis.T @ basis
    return FeatureMonitor(
        tuple(mean.tolist()),
        tuple(tuple(row) for row in basis.tolist()),
        tuple(variances.tolist()),
        max(float(np.mean(np.sum(residual**2, axis=1))), MIN_VARIANCE),
        np.inf,
        alpha,
    )
