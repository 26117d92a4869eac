"""Domain randomisation: typed ranges, presets, determinism per seed, looks applied in place."""

from __future__ import annotations

import dataclasses
import pickle
import re

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import saferace  # noqa: F401  - registers the tasks
from saferace.envs.randomization import (
    PHYSICS_PRESETS,
    PRESET_NAMES,
    VISUAL_PRESETS,
    PhysicsRandomization,
    RandomizationError,
    VisualRandomization,
)
from saferace.registry import TASKS

TASK_IDS = sorted(TASKS)


def onboard(env, seed: int) -> tuple[np.ndarray, dict]:
    observation, info = env.reset(seed=seed)
    return observation["image"], info


@pytest.mark.parametrize("preset", PRESET_NAMES)
@pytest.mark.parametrize("task_id", TASK_IDS)
def test_every_preset_passes_the_env_checker(task_id: str, preset: str):
    env = gym.make(
        task_id, track="lab", render_mode="rgb_array", randomize=preset, physics_randomize=preset
    )
    check_env(env.unwrapped, skip_render_check=False)
    env.close()


@pytest.mark.parametrize("preset", ["mild", "strong"])
def test_same_seed_same_look_and_car_and_episode(preset: str):
    envs = [
        gym.make(
            "saferace/RacingLine-v0", track="technical", randomize=preset, physics_randomize=preset
        )
        for _ in range(2)
    ]
    first = [env.reset(seed=4) for env in envs]
    np.testing.assert_array_equal(first[0][0]["image"], first[1][0]["image"])
    assert first[0][1]["look"] == first[1][1]["look"]
    assert first[0][1]["car"] == first[1][1]["car"]
    for step in range(40):
        action = np.array([0.1 * np.sin(step / 4.0), 1.0], np.float32)
        results = [env.step(action) for env in envs]
        np.testing.assert_array_equal(results[0][0]["image"], results[1][0]["image"])
        assert results[0][4]["x_m"] == results[1][4]["x_m"]
    for env in envs:
        env.close()


def test_seeds_draw_different_looks_and_a_seed_redraws_its_own():
    env = gym.make("saferace/CenterLine-v0", track="technical", randomize="strong")
    image_0, info_0 = onboard(env, 0)
    image_1, info_1 = onboard(env, 1)
    assert info_0["look"] != info_1["look"]
    assert np.abs(image_0.astype(int) - image_1.astype(int)).mean() > 5.0
    again, info_again = onboard(env, 0)  # after another look was applied in place
    np.testing.assert_array_equal(again, image_0)
    assert info_again["look"] == info_0["look"]
    env.close()


def test_the_none_preset_is_the_plain_scene():
    images = []
    for randomize in (None, "none", VisualRandomization()):
        env = gym.make("saferace/CenterLine-v0", track="lab", randomize=randomize)
        image, info = onboard(env, 3)
        assert "look" not in info and "car" not in info
        images.append(image)
        env.close()
    for image in images[1:]:
        np.testing.assert_array_equal(image, images[0])


def test_one_range_changes_the_image_as_asked():
    brighter = VisualRandomization(light_intensity=(1.5, 1.5))
    darker = VisualRandomization(light_intensity=(0.5, 0.5))
    means = []
    for randomize in (darker, brighter):
        env = gym.make("saferace/CenterLine-v0", track="lab", randomize=randomize)
        image, info = onboard(env, 0)
        assert info["look"]["light_intensity"] == randomize.light_intensity[0]
        means.append(image.mean())
        env.close()
    assert means[1] > means[0] + 20.0


def test_dashed_lines_leave_gaps_along_the_lane():
    dashed = VisualRandomization(line_dashed_probability=1.0)
    env = gym.make("saferace/CenterLine-v0", track="oval", randomize=dashed).unwrapped
    env.reset(seed=0)
    model = env.model
    assert model.geom_rgba[model.geom("left_line").id, 3] == 0.0  # the solid line hidden
    assert model.geom_rgba[model.geom("left_dashes").id, 3] == 1.0
    solid = gym.make("saferace/CenterLine-v0", track="oval", randomize="mild").unwrapped
    solid.reset(seed=0)
    assert solid.model.geom_rgba[solid.model.geom("left_dashes").id, 3] == 0.0
    env.close()
    solid.close()


def test_wider_lines_move_only_their_inner_edge():
    env = gym.make(
        "saferace/CenterLine-v0",
        track="lab",
        randomize=VisualRandomization(line_width_scale=(2.0, 2.0)),
    ).unwrapped
    model = env.model

    def pairs(mesh: int) -> np.ndarray:
        start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
        return model.mesh_vert[start : start + count].reshape(-1, 2, 3)

    built_mesh = model.mesh("left_line_mesh").id
    built = pairs(built_mesh).copy()
    env.reset(seed=0)
    shown = model.geom_dataid[model.geom("left_line").id]
    assert shown != built_mesh  # the line drawn is a bank entry's reshaped copy
    moved = pairs(shown)
    np.testing.assert_array_equal(moved[:, 0], built[:, 0])
    built_width = np.linalg.norm(built[:, 1] - built[:, 0], axis=1)
    np.testing.assert_allclose(
        np.linalg.norm(moved[:, 1] - moved[:, 0], axis=1), 2 * built_width, rtol=1e-5
    )
    env.close()


def test_physics_randomisation_changes_the_car_and_restores_it_per_draw():
    env = gym.make("saferace/CenterLine-v0", track="lab", physics_randomize="strong").unwrapped
    plain = gym.make("saferace/CenterLine-v0", track="lab").unwrapped
    chassis = env.model.body("chassis").id
    built_mass = plain.model.body_mass[chassis]
    tyre = plain.model.geom("rear_left_tyre").id
    masses = set()
    for seed in range(3):
        _, info = env.reset(seed=seed)
        car = info["car"]
        assert env.model.body_mass[chassis] == pytest.approx(built_mass * car["mass_scale"])
        assert env.model.geom_friction[tyre, 0] == pytest.approx(
            plain.model.geom_friction[tyre, 0] * car["friction_scale"]
        )
        assert env.drivetrain.motor_stall_torque_nm == pytest.approx(
            plain.params.motor_stall_torque_nm * car["motor_scale"]
        )
        assert env.params == plain.params  # what a controller knows stays nominal
        masses.add(round(float(env.model.body_mass[chassis]), 6))
    assert len(masses) == 3
    env.close()
    plain.close()


def test_pickled_env_keeps_its_look_and_car_and_continues_identically():
    env = gym.make(
        "saferace/RacingLine-v0", track="varying", randomize="strong", physics_randomize="strong"
    ).unwrapped
    env.reset(seed=2)
    for _ in range(5):
        env.step(np.array([0.0, 1.0]))
    clone = pickle.loads(pickle.dumps(env))
    for step in range(10):
        action = np.array([0.05 * np.sin(step), 0.5])
        a, b = env.step(action), clone.step(action)
        np.testing.assert_array_equal(a[0]["image"], b[0]["image"])
        assert (a[4]["x_m"], a[4]["v_x_mps"]) == (b[4]["x_m"], b[4]["v_x_mps"])
    env.close()
    clone.close()


@pytest.mark.parametrize(
    ("ranges", "message"),
    [
        (dict(light_intensity=(-0.5, 1.0)), "light_intensity must lie within"),
        (dict(asphalt_brightness=(1.2, 0.8)), "asphalt_brightness is an empty range"),
        (dict(camera_fovy_deg=(0.0, float("nan"))), "two finite numbers"),
        (dict(line_dashed_probability=1.5), "probability in"),
        (dict(image_noise_std=3.0), "a (low, high) pair"),
    ],
)
def test_bad_visual_ranges_are_refused_with_the_field_named(ranges: dict, message: str):
    with pytest.raises(RandomizationError, match=re.escape(message)):
        VisualRandomization(**ranges)


def test_bad_physics_ranges_and_presets_are_refused():
    with pytest.raises(RandomizationError, match="friction_scale is an empty range"):
        PhysicsRandomization(friction_scale=(1.1, 0.9))
    with pytest.raises(RandomizationError, match="mass_scale must lie within"):
        PhysicsRandomization(mass_scale=(0.0, 1.0))
    with pytest.raises(RandomizationError, match="unknown VisualRandomization preset 'wild'"):
        gym.make("saferace/CenterLine-v0", track="lab", randomize="wild")
    with pytest.raises(RandomizationError, match="expected a preset name"):
        gym.make("saferace/CenterLine-v0", track="lab", physics_randomize=1.0)


def test_presets_grow_from_none_to_strong():
    for presets in (VISUAL_PRESETS, PHYSICS_PRESETS):
        assert presets["none"].is_identity
        for field in dataclasses.fields(presets["none"]):
            if field.name == "asphalt_textured_probability":
                continue  # a share of looks, not a spread: strong textures half of them
            widths = []
            for name in PRESET_NAMES:
                value = getattr(presets[name], field.name)
                widths.append(value if isinstance(value, float) else value[1] - value[0])
            assert widths[0] <= widths[1] <= widths[2], field.name


def test_a_look_picks_its_sky_and_asphalt_from_banks_without_uploading_a_texture(
    monkeypatch: pytest.MonkeyPatch,
):
    import mujoco

    from saferace.envs.scene import TEXTURE_BANK_SIZE

    env = gym.make("saferace/CenterLine-v0", track="technical", randomize="strong")
    onboard(env, 0)  # makes the renderer, which uploads the model with its banks

    def no_texture_upload(*args):
        raise AssertionError("a look uploaded a texture")

    monkeypatch.setattr(mujoco, "mjr_uploadTexture", no_texture_upload)
    top_rows: dict[int, np.ndarray] = {}  # the sky, above the horizon
    for seed in range(1, 25):
        image, info = onboard(env, seed)
        entry = info["look"]["sky_bank_entry"]
        assert 0 <= entry < TEXTURE_BANK_SIZE
        top_rows.setdefault(entry, image[:3].astype(float).mean(axis=(0, 1)))
    env.close()
    assert len(top_rows) >= 8  # the looks spread over the bank
    colours = np.array(list(top_rows.values()))
    assert np.ptp(colours, axis=0).max() > 20.0  # and the entries are different skies


def test_two_environments_with_the_same_ranges_draw_the_same_look_per_seed():
    images = []
    for _ in range(2):
        env = gym.make("saferace/CenterLine-v0", track="lab", randomize="strong")
        images.append(onboard(env, 7)[0])
        env.close()
    np.testing.assert_array_equal(images[0], images[1])
