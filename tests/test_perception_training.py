"""What the generic perception model trains and calibrates on: distinct tracks apart from
each other, mirrored frames, and a calibration that scores the lateral offset as well as the
heading (each the survivor of a mutation run, ``docs/results/tests.md``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from saferace.cache import CACHE_VARIABLE
from saferace.learning import perception
from saferace.learning.calibration import CALIBRATED_OUTPUTS
from saferace.learning.checkpoint import CONFORMAL_KEY, load_checkpoint
from saferace.learning.perception import RECIPES, inside_frames, rounds_folder, write_tracks
from saferace.learning.rounds import FrameSet
from saferace.learning.training_data import network_data
from saferace.learning.validation import predict_frames
from saferace.safety.uncertainty.conformal import normalised_scores


@pytest.mark.parametrize("name", sorted(RECIPES))
def test_a_recipe_trains_and_calibrates_on_distinct_tracks_none_in_both(name: str):
    """A seed named twice is one track driven twice (fewer tracks than the recipe says); a
    calibration track the network trained on voids the calibration's guarantee."""
    recipe = RECIPES[name]
    train, calibration = recipe.train_track_seeds, recipe.calibration_track_seeds
    assert len(set(train)) == len(train) >= 3
    assert len(set(calibration)) == len(calibration) >= 2
    assert not set(train) & set(calibration)


def test_every_recipe_trains_its_network_on_mirrored_frames_too(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
):
    """Mirroring adds each frame with left and right swapped: a random track runs one way
    round, and without it the network would see most of a track's bends turn one way."""
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path))
    mirrored: list[bool] = []

    def train(frames, config, progress, resume, mirror):  # type: ignore[no-untyped-def]
        mirrored.append(mirror)
        return None, None, {}

    monkeypatch.setattr(perception, "train_networks", train)
    monkeypatch.setattr(perception, "load_rounds", lambda folders: folders)
    monkeypatch.setattr(perception, "targets_of", lambda recipe, frames: frames)
    monkeypatch.setattr(perception, "save_checkpoint", lambda *arguments: None)
    for recipe in RECIPES.values():
        perception.train_state_network(recipe, [], progress=False)
    assert mirrored == [True] * len(RECIPES)


def test_the_calibration_scores_each_frame_by_its_offset_and_its_heading(quick_perception: Path):
    """A calibration frame's score is its larger error of the two outputs the filter reads,
    each in its own spread: scored on one alone, the other's interval would be whatever
    that one's scale gives it."""
    recipe = RECIPES["quick"]
    loaded = load_checkpoint(perception.build_perception_model(recipe, progress=False))
    parts = [
        inside_frames(recipe, rounds_folder(recipe, track), track)
        for track in write_tracks(recipe, "calibration")
    ]
    frames = FrameSet(
        {name: np.concatenate([part[name] for part in parts]) for name in parts[0].arrays}, []
    )
    prediction = predict_frames(loaded.state, network_data(frames)["state"], 1)
    outputs = len(CALIBRATED_OUTPUTS)
    assert outputs == 2  # e_y and e_psi
    scores = normalised_scores(
        prediction.mean[:, :outputs], prediction.std[:, :outputs], frames["state"][:, :outputs]
    )
    recorded = np.asarray(loaded.metadata[CONFORMAL_KEY]["scores"])
    np.testing.assert_allclose(recorded, np.sort(scores), rtol=1e-5)
    heading_only = normalised_scores(
        prediction.mean[:, 1:2], prediction.std[:, 1:2], frames["state"][:, 1:2]
    )
    assert not np.allclose(np.sort(heading_only), recorded, rtol=1e-5)  # the offset counts


def test_the_reckless_drivers_collect_behind_the_filter_and_the_expert_without(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
):
    """Unfiltered, a reckless driver leaves its lane within a second and its frames show the
    grass; behind the filter it weaves and drifts inside the lane, the frames the network
    must read; the expert needs no filter. Each drive of a track has a seed of its own (its
    look and steering noise drawn apart from the others')."""
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path))
    configs = []

    def collect(folder, config, progress):  # type: ignore[no-untyped-def]
        configs.append(config)
        return type("Round", (), {"frame_count": 1})()

    monkeypatch.setattr(perception, "collect_round", collect)
    recipe = RECIPES["default"]
    perception.collect_track(recipe, tmp_path / "train_90001.csv", "train", 0)
    kinds = {config.agent: config.safety.kind for config in configs}
    assert kinds == {
        "expert": "none",
        **{driver: "cbf" for driver in recipe.drivers if driver != "expert"},
    }
    assert len({config.seeds for config in configs}) == len(configs) == len(recipe.drivers)


@pytest.mark.parametrize("part", ["train", "calibration"])
def test_every_track_is_driven_in_each_task_and_look_of_its_part(part: str):
    """Each track shows the network both lane tasks and (training) both looks, the drivers
    taking turns; a track driven in one task alone would teach a line by its track."""
    recipe = RECIPES["default"]
    looks = recipe.looks if part == "train" else recipe.calibration_looks
    for track_index in range(4):
        drives = recipe.drives(part, track_index)
        assert [driver for driver, _, _ in drives] == list(recipe.drivers)
        assert {task for _, task, _ in drives} == set(recipe.tasks)
        assert {look for _, _, look in drives} == set(looks)
