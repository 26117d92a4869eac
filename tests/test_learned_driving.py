"""Behaviour cloning as a sanity check of the whole path: collect, train, drive (a tiny one
and one at the paper's image size, both in the slow suite)."""

from __future__ import annotations

from pathlib import Path

import pytest

from saferace.envs.racing_env import DEFAULT_CONTROL_HZ
from saferace.eval.runner import evaluate
from saferace.learning.collect import CollectionConfig, Perturbation, collect_round
from saferace.learning.commands import train_and_report
from saferace.learning.configs import EpisodeSettings
from saferace.learning.training import TrainConfig

#: The tiny version: 32x32 images, 10 s drives (a lap of lab takes the expert 7.6 s).
TINY_IMAGE, TINY_SECONDS = 32, 10.0


@pytest.mark.slow
def test_a_tiny_cloned_expert_laps_lab_inside_its_lane(tmp_path: Path):
    """Six perturbed 10 s expert drives at 32x32, ten epochs: the cloned driver laps lab
    inside the lane, near the expert's line and time (about 85 s on 2 cores: the default
    suite's longest test, so in the slow one)."""
    episode = EpisodeSettings(
        laps=1, max_seconds=TINY_SECONDS, image_size=TINY_IMAGE, expert_model="kinematic"
    )
    rounds = CollectionConfig(
        task="CenterLine",
        track="lab",
        seeds=tuple(range(6)),
        episode=episode,
        perturbation=Perturbation(0.05),
    )
    collect_round(tmp_path / "data", rounds, progress=False)
    checkpoint = tmp_path / "tiny.pt"
    settings = TrainConfig(epochs=10, val_stretch=None)
    train_and_report([tmp_path / "data"], checkpoint, settings, mc_samples=3, progress=False)
    env = {"image_size": (TINY_IMAGE, TINY_IMAGE), "max_steps": int(20 * DEFAULT_CONTROL_HZ)}
    expert, cloned = (
        evaluate(agent, "CenterLine", "lab", [7], model="kinematic", env_kwargs=env,
                 progress=False)[0]["summary"]
        for agent in ("expert", f"learned:{checkpoint}")
    )  # fmt: skip
    assert cloned["laps_completed"] == 1 and cloned["time_outside_lane_s"] == 0.0
    assert cloned["mean_lap_time_s"] == pytest.approx(expert["mean_lap_time_s"], rel=0.2)
    assert cloned["max_abs_deviation_m"] < 0.15  # the lane leaves the car 0.25 m either side


@pytest.mark.slow
def test_cloned_expert_drives_three_laps_of_lab(tmp_path: Path):
    """Networks trained on perturbed expert rounds of lab lap it like the expert (~9 min)."""
    data = tmp_path / "data"
    perturbed = CollectionConfig(
        task="CenterLine", track="lab", seeds=tuple(range(6)), perturbation=Perturbation(0.05)
    )
    collect_round(data, perturbed, progress=False)
    collect_round(data, CollectionConfig(task="CenterLine", track="lab", seeds=(100,)), False)
    checkpoint = tmp_path / "cloned.pt"
    train_and_report([data], checkpoint, TrainConfig(epochs=10), progress=False)
    expert, cloned = (
        evaluate(agent, "CenterLine", "lab", [0], laps=3, progress=False)[0]["summary"]
        for agent in ("expert", f"learned:{checkpoint}")
    )
    assert cloned["laps_completed"] == 3 and cloned["time_outside_lane_s"] == 0.0
    assert cloned["mean_lap_time_s"] == pytest.approx(expert["mean_lap_time_s"], rel=0.1)
    assert cloned["max_abs_deviation_m"] < 0.2  # the lane leaves the car 0.25 m either side
