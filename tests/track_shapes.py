"""Track outlines the tests build their own lanes from."""

from __future__ import annotations

import numpy as np


def paperclip(
    legs_apart_m: float, straight_m: float = 8.0, spacing_m: float = 0.2
) -> tuple[np.ndarray, np.ndarray]:
    """``x, y`` of a paperclip lap: two straights ``legs_apart_m`` apart joined by half
    circles (counter-clockwise), the hairpin of a circuit whose legs meet."""
    radius = legs_apart_m / 2.0
    turn = np.pi * radius
    s = np.arange(0.0, 2.0 * (straight_m + turn), spacing_m)
    lap = s % (straight_m + turn)  # each half: a straight, then a half circle
    first_half = s < straight_m + turn
    angle = -np.pi / 2.0 + (lap - straight_m) / radius
    on_turn = straight_m / 2.0 + radius * np.cos(angle)
    x = np.where(lap < straight_m, lap - straight_m / 2.0, on_turn)
    y = np.where(lap < straight_m, -radius, radius * np.sin(angle))
    return np.where(first_half, x, -x), np.where(first_half, y, -y)
