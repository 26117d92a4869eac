"""Rounds exported to Minari load back with ``minari.load_dataset``, frame for frame."""

from __future__ import annotations

import os
from pathlib import Path

import minari
import numpy as np
import pytest

from saferace.errors import SafeRaceError
from saferace.learning.collect import collect_round
from saferace.learning.configs import CollectionConfig, EpisodeSettings
from saferace.learning.minari_export import export_minari
from saferace.learning.rounds import round_dirs, round_episodes


@pytest.fixture(scope="module")
def rounds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two rounds (of two and one short episodes) on lab's racing line."""
    folder = tmp_path_factory.mktemp("rounds") / "data"
    for seeds in ((0, 1), (2,)):
        config = CollectionConfig(
            task="RacingLine",
            track="lab",
            seeds=seeds,
            episode=EpisodeSettings(laps=1, max_seconds=2.0),
        )
        collect_round(folder, config, progress=False)
    return folder


def test_round_trip_keeps_frames_actions_and_labels(rounds: Path, tmp_path: Path, monkeypatch):
    export_minari([rounds], "saferace/lab-test-v0", datasets_dir=tmp_path)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    dataset = minari.load_dataset("saferace/lab-test-v0")
    expected = [e for folder in round_dirs(rounds) for e in round_episodes(folder)[1]]
    assert dataset.total_episodes == len(expected) == 3
    for episode, frames in zip(dataset.iterate_episodes(), expected, strict=True):
        np.testing.assert_array_equal(episode.observations["image"], frames["image"])
        np.testing.assert_array_equal(episode.observations["velocity"], frames["velocity"])
        np.testing.assert_array_equal(episode.actions, frames["applied_action"][:-1])
        for label in ("expert", "state", "driver_action", "s_m", "time_s"):
            np.testing.assert_array_equal(episode.infos[label], frames[label])
        assert len(episode.rewards) == len(frames["s_m"]) - 1
        assert episode.rewards.sum() > 0.5  # the car made progress
        assert episode.truncations[-1] and not episode.terminations.any()
    env = dataset.recover_environment()
    assert env.unwrapped.track.name == "lab" and env.observation_space == dataset.observation_space
    env.close()


def test_an_existing_name_and_mixed_rounds_are_refused(rounds: Path, tmp_path: Path):
    root_before = os.environ.get("MINARI_DATASETS_PATH")
    export_minari([rounds], "saferace/lab-twice-v0", datasets_dir=tmp_path)
    with pytest.raises(SafeRaceError, match="exists already"):
        export_minari([rounds], "saferace/lab-twice-v0", datasets_dir=tmp_path)
    other = tmp_path / "oval"
    episode = EpisodeSettings(laps=1, max_seconds=1.0)
    collect_round(other, CollectionConfig(task="RacingLine", track="oval", episode=episode), False)
    with pytest.raises(SafeRaceError, match="mix"):
        export_minari([rounds, other], "saferace/mixed-v0", datasets_dir=tmp_path)
    with pytest.raises(SafeRaceError, match="no complete collection round"):
        export_minari([tmp_path / "nothing"], "saferace/none-v0", datasets_dir=tmp_path)
    assert os.environ.get("MINARI_DATASETS_PATH") == root_before  # Minari's root restored
