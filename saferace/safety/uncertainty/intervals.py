"""Intervals of the perceived lane state: the set a robust filter must hold the car safe over.

A state source gives samples of ``[e_y, e_psi, kappa]``; the robust filter needs a box that
holds the truth. A source that knows its calibration says so through ``interval(samples)``
(:class:`ConformalStateSource`: ``mean +- q sigma`` from a conformal calibration); any other
source gets ``mean +- z std`` of its samples, ``z`` the filter's confidence quantile (the
chance constraints' own assumption, calibrated or not). The truth itself (one sample) is a
point.
"""

from __future__ import annotations

import itertools
from functools import cache
from typing import Any, Protocol, TypeGuard, runtime_checkable

import numpy as np

from saferace.errors import SafeRaceError
from saferace.safety.uncertainty.conformal import ConformalCalibration, SpreadMonitor
from saferace.safety.uncertainty.state_sources import StateSource


@runtime_checkable
class IntervalStateSource(StateSource, Protocol):
    """A state source that also knows the interval its samples stand for."""

    def interval(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(lower, upper)`` of ``[e_y, e_psi, kappa]`` for this step's ``samples``."""
        ...


@runtime_checkable
class MonitoredStateSource(StateSource, Protocol):
    """A state source that can tell when its input is unlike what it was calibrated on."""

    def monitor(self, samples: np.ndarray) -> tuple[float | None, bool]:
        """``(score, alarm)`` of this step's ``samples`` (``None``: no monitor)."""
        ...


@runtime_checkable
class FeatureSource(StateSource, Protocol):
    """A state source that keeps what its network saw in the last frame it predicted."""

    last_features: np.ndarray | None


def gives_intervals(source: StateSource) -> TypeGuard[IntervalStateSource]:
    """``isinstance(source, IntervalStateSource)``, judged once per class (see
    :func:`_class_check`)."""
    return _class_check(type(source), IntervalStateSource)


def has_monitor(source: StateSource) -> TypeGuard[MonitoredStateSource]:
    """``isinstance(source, MonitoredStateSource)``, judged once per class."""
    return _class_check(type(source), MonitoredStateSource)


@cache
def _class_check(source_type: type, protocol: Any) -> bool:
    """Whether a class has a protocol's methods: a runtime protocol check costs about
    10 us, a hundredth of a filter's step budget, and a class keeps its methods."""
    return issubclass(source_type, protocol)


def state_interval(
    source: StateSource, samples: np.ndarray, z: float
) -> tuple[np.ndarray, np.ndarray]:
    """The interval ``source`` gives for ``samples``, or ``mean +- z std`` of them."""
    return interval_about(source, samples, samples.mean(axis=0), samples.std(axis=0), z)


def interval_about(
    source: StateSource, samples: np.ndarray, mean: np.ndarray, std: np.ndarray, z: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`state_interval` with the samples' ``mean`` and ``std`` already at hand."""
    if gives_intervals(source):
        return source.interval(samples)
    return mean - z * std, mean + z * std


def interval_points(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The box's corners and centre, ``(k, 3)``: where a robust filter checks its barriers
    (exactly the box's extremes where a condition is monotone in each state, as the lane
    barriers are in ``e_y`` and, for headings within ``+-pi/2``, in ``e_psi``). A degenerate
    side adds no corners: a point interval is one point."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    sides = [(lo,) if lo == hi else (lo, hi) for lo, hi in zip(lower, upper, strict=True)]
    corners = np.array(list(itertools.product(*sides)), dtype=float)
    if len(corners) == 1:
        return corners
    return np.vstack([corners, 0.5 * (lower + upper)])


class ConformalStateSource:
    """Another source's samples, with the interval of a conformal calibration of its spread:
    ``mean +- scale * std`` of the samples (a
    :class:`~saferace.safety.uncertainty.conformal.ConformalCalibration` fitted on frames the source
    never trained on), and the calibration's out-of-distribution monitor: on the samples'
    spread, or on the features the source's network saw (a
    :class:`~saferace.safety.uncertainty.feature_monitor.FeatureMonitor`, for a
    :class:`FeatureSource`)."""

    def __init__(self, source: StateSource, calibration: ConformalCalibration) -> None:
        self.source = source
        self.calibration = calibration

    def reset(self, seed: int | None = None) -> None:
        self.source.reset(seed)

    def samples(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        return self.source.samples(observation, info)

    def interval(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.calibration.interval(samples.mean(axis=0), samples.std(axis=0))

    def monitor(self, samples: np.ndarray) -> tuple[float | None, bool]:
        monitor = self.calibration.monitor
        if monitor is None:
            return None, False
        if isinstance(monitor, SpreadMonitor):
            return monitor.raises(samples.std(axis=0)[: len(monitor.reference)])
        features = self.source.last_features if isinstance(self.source, FeatureSource) else None
        if features is None:
            raise SafeRaceError(
                "this calibration's monitor looks at a network's features, and the state "
                f"source {type(self.source).__name__} has none: recalibrate with --monitor spread"
            )
        return monitor.raises(features)

    def describe(self) -> dict:
        inner: dict[str, Any] = getattr(self.source, "describe", dict)()
        return {**inner, "conformal": self.calibration.summary()}
