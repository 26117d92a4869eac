"""(Slow) Behaviour cloning as a sanity check of the whole path: collect, train, drive."""

from __future__ import annotations

from pathlib import Path

import pytest

from saferace.eval.runner import evaluate
from saferace.learning.collect import CollectionConfig, Perturbation, collect_round
from saferace.learning.commands import train_and_report
from saferace.learning.training import TrainConfig


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
