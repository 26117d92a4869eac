"""Shared fixtures: built-in tracks and a generator of tracks the repository has never seen."""

from __future__ import annotations

from pathlib import Path

import pytest

from saferace.track import Track, builtin_track_names
from saferace.track.random_track import write_random_track


@pytest.fixture(params=builtin_track_names())
def builtin_track(request: pytest.FixtureRequest) -> Track:
    return Track.load(request.param)


@pytest.fixture(params=[11, 23])
def unseen_track_csv(request: pytest.FixtureRequest, tmp_path: Path) -> Path:
    """A CSV track the repository has never seen, clockwise for one seed."""
    return write_random_track(tmp_path / f"unseen_{request.param}.csv", request.param)
