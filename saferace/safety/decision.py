"""What passes through the safety filter: an agent's action in, the filter's decision out."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from gymnasium.utils import RecordConstructorArgs

#: Why the filter stopped trusting its state source in a step (``SafetyDecision.fallback``):
#: the out-of-distribution monitor raised, no control satisfied the robust constraints, the
#: solver failed, or braking back onto the line after the action would leave the lane.
FALLBACK_REASONS = ("", "alarm", "infeasible", "solver", "backup")
#: What acted in a step (``SafetyDecision.mode``): the constraints held on this frame's state
#: (``certified``); they held on the last trusted state carried forward by odometry, this
#: frame being in doubt (``propagated``; the predictive filter: its last certified plan's
#: rest); neither held, and the fallback slowed the car to a speed its set fits at, a stop
#: where none does (``stopping``; ``fallback`` says why).
MODES = ("certified", "propagated", "stopping")


def decision_mode(fallback: str, propagated: bool) -> str:
    """The :data:`MODES` entry of a step with ``fallback`` (a car's, ``"car"``, is no
    fallback of the lane) whose state was ``propagated`` from the last trusted one."""
    if fallback in ("", "car"):
        return "propagated" if propagated else "certified"
    return "stopping"


@dataclass(frozen=True)
class NominalAction:
    """An agent's action with the spread of its own uncertainty (e.g. its MC-dropout std).

    Agents may return this instead of a plain action; the filter then weighs each control's
    deviation by ``1 / std^2``, so it bends the controls the agent is least sure of.
    """

    mean: np.ndarray
    std: np.ndarray | None = None


def nominal_parts(action: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """``(mean, std or None)`` of a plain action or a :class:`NominalAction`."""
    if isinstance(action, NominalAction):
        std = None if action.std is None else np.asarray(action.std, dtype=float).ravel()
        return np.asarray(action.mean, dtype=float).ravel(), std
    return np.asarray(action, dtype=float).ravel(), None


@dataclass(frozen=True)
class SafetyDecision:
    """What the filter did in one step (``info["safety"]``); per-barrier values by name.

    ``barriers`` are the estimated ``h`` (mean over state samples, or the lowest over the
    interval's points in the robust mode; m for the lanes, rad for the heading);
    ``constraints`` the HOCBF condition ``psi_m`` at the filtered action (likewise, ``>= 0``
    holds); ``tightening`` the chance-constraint margin ``Phi^-1(eta) * std`` (the spread at
    the agent's acceleration); ``slacks`` what each constraint needed. ``state_mean`` and
    ``state_std`` are the ``[e_y, e_psi, kappa]`` the filter believed (the curvature from
    the map where it takes it from there), ``state_lower`` and ``state_upper`` the interval
    it held the state to (``mean +- z std`` in the chance mode), ``state_true`` the
    simulator's at the same moment and ``covered`` whether the interval held it.
    ``monitor_score`` is the out-of-distribution score (None without a monitor), ``stale``
    whether the frame was stale (repeated while the car moved, or blank), ``alarm``
    whether the filter was in doubt of its state source (the monitor passed its threshold,
    the frame was stale, or its interval contradicted the carried set); ``fallback`` is why
    the filter braked towards a speed the interval fits at (one of
    :data:`FALLBACK_REASONS`, ``""``: it did not), ``mode`` what acted (one of
    :data:`MODES`). The actions are the wheels' angles: the command sent was the filtered
    one less ``steering_offset_rad``, the offset the filter judged the steering's centre to
    be off by (:mod:`~saferace.safety.uncertainty.steering_trim`). ``clipped``: the filter
    answered an action outside the actuators' limits, and it was clipped to them (a filter
    of the protocol, :mod:`saferace.safety.filter_protocol`; ours stay within them).
    """

    nominal_action: list[float]
    filtered_action: list[float]
    state_true: list[float]
    state_mean: list[float]
    state_std: list[float]
    state_lower: list[float]
    state_upper: list[float]
    covered: bool
    barriers: dict[str, float]
    constraints: dict[str, float]
    tightening: dict[str, float]
    slacks: dict[str, float]
    intervened: bool
    monitor_score: float | None
    stale: bool
    alarm: bool
    fallback: str
    status: str
    iterations: int
    solve_time_s: float
    filter_time_s: float
    n_samples: int
    mode: str
    steering_offset_rad: float = 0.0
    clipped: bool = False

    def as_dict(self, timed: bool = True) -> dict[str, Any]:
        """The decision's fields; ``timed=False``: its wall-clock times 0, so that the same
        seed and actions give the same record."""
        fields = asdict(self)
        if not timed:
            fields["solve_time_s"] = fields["filter_time_s"] = 0.0
        return fields


def record_args(wrapper: Any, arguments: dict[str, Any]) -> None:
    """Record a filter wrapper's constructor ``arguments`` (its ``locals()`` on entry) as
    gymnasium's ``RecordConstructorArgs`` does, so that ``env.spec`` can name and remake
    it; the first call wins (a subclass's, before its parent's), and nothing is copied (a
    state source may hold a network)."""
    kept = {name: value for name, value in arguments.items() if name not in IMPLICIT}
    RecordConstructorArgs.__init__(wrapper, _disable_deepcopy=True, **kept)


#: A constructor's ``locals()`` that are not its arguments.
IMPLICIT = ("self", "env", "__class__")
