"""What a safety filter reads from its inputs each step: the agent's action and the state.

Shared by the filter families (:mod:`saferace.safety.cbf.filter`,
:mod:`saferace.safety.predictive.filter`): the action checked and given its spread, the state
source's samples, the interval it holds the state to and its monitor's verdict, and the
record of all that in a :class:`~saferace.safety.decision.SafetyDecision`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from saferace.safety.uncertainty.intervals import has_monitor, interval_about
from saferace.safety.uncertainty.state_sources import StateSource


def checked_action(
    action: Any, action_std: Any, default_std: np.ndarray, min_std: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The agent's ``[steer, accel]``, checked, and its spread (``default_std`` where it
    gives none), floored at ``min_std``."""
    nominal = np.asarray(action, dtype=float).ravel()
    if nominal.shape != (2,) or not np.all(np.isfinite(nominal)):
        raise ValueError(f"action must be 2 finite numbers [steer, accel], got {action!r}")
    spread = default_std if action_std is None else np.asarray(action_std, dtype=float)
    return nominal, np.maximum(spread, min_std)


@dataclass(frozen=True)
class StateEstimate:
    """One step's belief of the lane state ``[e_y, e_psi, kappa]``: the source's samples
    (with their mean and standard deviation), the interval it holds the state to and
    whether that is ``bounded``, the monitor's score (None without a monitor), whether the
    frame was ``stale`` (:mod:`~saferace.safety.uncertainty.stale_frames`) and whether the
    monitor raised, the interval is unbounded or the frame stale (``alarm``: the source is
    in doubt)."""

    samples: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    monitor_score: float | None
    alarm: bool
    map_curvature: bool
    bounded: bool
    stale: bool = False

    def fields(self, info: dict[str, Any], kappa_mean: float) -> dict[str, Any]:
        """The decision's record of the state: the simulator's truth, the belief and
        whether the interval covered the truth (the map's curvature, no estimate, is not
        checked)."""
        truth = np.array([info[name] for name in ("e_y_m", "e_psi_rad", "kappa_radpm")], float)
        checked = slice(0, 2 if self.map_curvature else 3)
        lower, upper = self.lower, self.upper
        mean, std = self.mean.tolist(), self.std.tolist()
        return {
            "state_true": truth.tolist(),
            "state_mean": [*mean[:2], kappa_mean],
            "state_std": [*std[:2], 0.0 if self.map_curvature else std[2]],
            "state_lower": lower.tolist(),
            "state_upper": upper.tolist(),
            "stale": self.stale,
            "covered": bool(
                np.all(lower[checked] <= truth[checked])
                and np.all(truth[checked] <= upper[checked])
            ),
        }


def estimate_state(
    source: StateSource,
    observation: dict[str, np.ndarray],
    info: dict[str, Any],
    z: float,
    map_curvature_radpm: float | None,
    stale: bool = False,
) -> StateEstimate:
    """``source``'s belief this step, its interval ``mean +- z std`` where it has no own
    (its curvature pinned to ``map_curvature_radpm`` where given); a ``stale`` frame is
    no measurement."""
    samples = np.atleast_2d(source.samples(observation, info))
    mean, std = samples.mean(axis=0), samples.std(axis=0)
    lower, upper = interval_about(source, samples, mean, std, z)
    if map_curvature_radpm is not None:
        lower[2] = upper[2] = map_curvature_radpm
    score, alarm = source.monitor(samples) if has_monitor(source) else (None, False)
    bounded = bool(np.isfinite(lower).all() and np.isfinite(upper).all())
    return StateEstimate(
        samples,
        mean,
        std,
        lower,
        upper,
        score,
        alarm or not bounded or stale,  # an unbounded interval rules out no state at all
        map_curvature_radpm is not None,
        bounded,
        stale,
    )
