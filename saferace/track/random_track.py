"""Random closed tracks, for testing on tracks nobody tuned anything for."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from saferace.names import RANDOM_TRACK_RADIUS_M
from saferace.track.track_io import write_track_csv


def random_blob_points(
    seed: int, count: int = 300, radius_m: float = 6.0
) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random closed curve: an ellipse with a few random low-order harmonics."""
    rng = np.random.default_rng(seed)
    theta = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    radius = radius_m + (radius_m / 6.0) * sum(
        rng.uniform(-0.5, 0.5) * np.cos(k * theta + rng.uniform(0, 2 * np.pi)) for k in (2, 3)
    )
    return 1.4 * radius * np.cos(theta), radius * np.sin(theta)


def write_random_track(
    path: str | Path, seed: int, radius_m: float = 6.0, lane_width_m: float | None = None
) -> Path:
    """A random track CSV (clockwise for odd seeds) with varying half widths of 0.35-0.7 m;
    ``radius_m`` sets its size (the mean radius of its shorter axis). With ``lane_width_m``
    the half widths are scaled so that the lane is about that wide on average (the same
    variation along the lap, relative to the width)."""
    x, y = random_blob_points(seed, radius_m=radius_m)
    if seed % 2:
        x, y = x[::-1], y[::-1]
    rng = np.random.default_rng(seed)
    w_right = rng.uniform(0.45, 0.6) + 0.1 * np.sin(np.linspace(0, 4 * np.pi, len(x)))
    w_left = rng.uniform(0.45, 0.6) + 0.1 * np.cos(np.linspace(0, 2 * np.pi, len(x)))
    if lane_width_m is not None:
        if lane_width_m <= 0.0:
            raise ValueError(f"lane_width_m must be positive, got {lane_width_m}")
        scale = lane_width_m / float(np.mean(w_right + w_left))
        w_right, w_left = scale * w_right, scale * w_left
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_track_csv(path, x, y, w_right, w_left)
    return path


def write_random_tracks(folder: str | Path, seeds: Iterable[int]) -> list[str]:
    """A random track per seed in ``folder`` (``random_SEED.csv``, of the experiments' size
    :data:`~saferace.names.RANDOM_TRACK_RADIUS_M`); their paths."""
    return [
        str(write_random_track(Path(folder) / f"random_{seed}.csv", seed, RANDOM_TRACK_RADIUS_M))
        for seed in seeds
    ]
