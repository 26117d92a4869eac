"""Shared fixtures: built-in tracks and a generator of tracks the repository has never seen."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from saferace.track import Track, builtin_track_names
from saferace.track.track_io import write_track_csv


def random_blob_points(seed: int, count: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random closed curve: an ellipse with a few random low-order harmonics."""
    rng = np.random.default_rng(seed)
    theta = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    radius = 6.0 + sum(
        rng.uniform(-0.5, 0.5) * np.cos(k * theta + rng.uniform(0, 2 * np.pi)) for k in (2, 3)
    )
    return 1.4 * radius * np.cos(theta), radius * np.sin(theta)


@pytest.fixture(params=builtin_track_names())
def builtin_track(request: pytest.FixtureRequest) -> Track:
    return Track.load(request.param)


@pytest.fixture(params=[11, 23])
def unseen_track_csv(request: pytest.FixtureRequest, tmp_path: Path) -> Path:
    """A CSV track the repository has never seen, clockwise for one seed."""
    x, y = random_blob_points(request.param)
    if request.param % 2:
        x, y = x[::-1], y[::-1]
    rng = np.random.default_rng(request.param)
    w_right = rng.uniform(0.45, 0.6) + 0.1 * np.sin(np.linspace(0, 4 * np.pi, len(x)))
    w_left = rng.uniform(0.45, 0.6) + 0.1 * np.cos(np.linspace(0, 2 * np.pi, len(x)))
    path = tmp_path / f"unseen_{request.param}.csv"
    write_track_csv(path, x, y, w_right, w_left)
    return path
