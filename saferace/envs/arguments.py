"""Checks of a racing task's constructor arguments, with errors that say what is allowed."""

from __future__ import annotations

from typing import Any

from saferace.errors import SafeRaceError


def check_task_arguments(
    image_size: tuple[int, ...],
    control_hz: float,
    physics_dt_s: float,
    max_laps: int,
    render_mode: str | None,
    metadata: dict[str, Any],
) -> None:
    """Raise a :class:`SafeRaceError` naming the first argument out of its range."""
    if len(image_size) != 2 or min(image_size) < 8 or max(image_size) > 480:
        raise SafeRaceError(
            f"image_size must be (height, width) between 8 and 480, got {image_size}"
        )
    if not 1.0 <= control_hz <= 1.0 / physics_dt_s:
        raise SafeRaceError(
            f"control_hz must be between 1 and the physics rate {1.0 / physics_dt_s:g}, "
            f"got {control_hz}"
        )
    if not 1e-4 <= physics_dt_s <= 0.01:
        raise SafeRaceError(f"physics_dt_s must be between 1e-4 and 0.01 s, got {physics_dt_s}")
    if max_laps < 1:
        raise SafeRaceError(f"max_laps must be at least 1, got {max_laps}")
    if render_mode is not None and render_mode not in metadata["render_modes"]:
        raise SafeRaceError(
            f"render_mode must be None or one of {metadata['render_modes']}, got {render_mode!r}"
        )
