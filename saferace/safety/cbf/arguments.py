"""The checks on a safety filter's constructor arguments, apart from the filter's logic:
each bad value named with what it must be, before anything is built."""

from __future__ import annotations

import math
from typing import Any

from saferace.names import SLACK_PENALTIES, UNCERTAINTY_MODES


def check_filter_arguments(arguments: dict[str, Any]) -> None:
    """Raise ``ValueError`` on the first of :class:`~saferace.safety.cbf.filter.SafetyFilter`'s
    ``arguments`` (its ``locals()`` on entry) that it cannot take."""
    uncertainty, slack_penalty = arguments["uncertainty"], arguments["slack_penalty"]
    if uncertainty not in UNCERTAINTY_MODES:
        raise ValueError(f"uncertainty must be one of {UNCERTAINTY_MODES}, got {uncertainty!r}")
    if slack_penalty not in SLACK_PENALTIES:
        raise ValueError(f"slack_penalty must be in {SLACK_PENALTIES}, got {slack_penalty!r}")
    for name in ("lateral_decel_mps2", "max_lateral_accel_mps2"):
        value = arguments[name]
        if value is not None and value <= 0.0:
            raise ValueError(f"{name} must be positive or None, got {value}")
    theta_max = arguments["theta_max"]
    if not 0.0 < theta_max < math.pi / 2:
        raise ValueError(f"need 0 < theta_max < pi/2, got {theta_max}")
    if min(arguments["action_std"]) <= 0.0 or min(arguments["min_action_std"]) <= 0.0:
        raise ValueError("action_std and min_action_std must be positive")
    for name in ("lane_margin_m", "creep_speed_mps", "opponent_noise_m"):
        if arguments[name] < 0.0:
            raise ValueError(f"{name} must be non-negative, got {arguments[name]}")
    passes = arguments["linearisation_passes"]
    if passes < 1:
        raise ValueError(f"linearisation_passes must be at least 1, got {passes}")
