"""Collection rounds: expert labels whoever drives, perturbations, the filter's flag, the CLI."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli

from saferace.envs.racing_env import DEFAULT_CONTROL_HZ
from saferace.errors import SafeRaceError
from saferace.eval.filters import FilterConfig
from saferace.learning.collect import SteeringNoise, collect_round
from saferace.learning.configs import CollectionConfig, EpisodeSettings, Perturbation
from saferace.learning.rounds import load_rounds


def collect(tmp_path: Path, **settings) -> tuple:
    settings.setdefault("task", "CenterLine")
    episode = EpisodeSettings(laps=1, max_seconds=3.0)
    config = CollectionConfig(track="lab", episode=episode, **settings)
    collected = collect_round(tmp_path / "data", config, progress=False)
    return collected, load_rounds([collected.path])


def test_expert_round_labels_are_its_own_actions(tmp_path: Path):
    collected, frames = collect(tmp_path)
    assert collected.frame_count == len(frames) == 60  # 3 s at 20 Hz, inside the lane
    assert np.array_equal(frames["driver_action"], frames["expert"][:, [0, 2]])
    clipped = np.clip(frames["driver_action"], [-0.36, -4.0], [0.36, 4.0])  # the action space
    assert np.array_equal(frames["applied_action"], clipped)
    # The speed profile asks only what the motors can push, so the plan stays within them.
    assert np.abs(frames["driver_action"][:, 1]).max() <= 4.0
    assert not frames["intervened"].any()
    assert np.all(np.diff(frames["s_m"]) > 0) and np.all(np.diff(frames["time_s"]) > 0)
    # The target-speed label is the plan's speed 0.25 s ahead: near the speed 5 steps later.
    later_speed = frames["velocity"][5:, 0]
    assert np.abs(frames["expert"][:-5, 1] - later_speed).mean() < 0.2
    assert np.abs(frames["expert"][:, 1] - frames["velocity"][:, 0]).mean() > 0.2
    config = frames.manifests[0]["config"]
    assert config["agent"] == "expert" and config["track"] == "lab"
    assert config["episodes"][0]["time_outside_lane_s"] == 0.0
    assert {"git_revision", "packages", "label_lookahead_s"} <= set(config)


def test_perturbed_driver_keeps_the_expert_label(tmp_path: Path):
    _, frames = collect(tmp_path, perturbation=Perturbation(0.1, 0.5))
    noise = frames["driver_action"][:, 0] - frames["expert"][:, 0]
    assert noise.std() > 0.03  # the car was pushed off its line ...
    assert np.array_equal(frames["driver_action"][:, 1], frames["expert"][:, 2])  # ... not braked
    assert np.abs(frames["state"][:, 0]).max() > 0.05  # and the frames show it off the line


def test_other_driver_through_the_filter(tmp_path: Path):
    safety = FilterConfig(kind="cbf")
    _, frames = collect(tmp_path, agent="drift", task="CenterLine", safety=safety)
    assert frames["intervened"].any()
    assert np.allclose(frames["driver_action"][:, 0], 0.1)  # the drift agent's constant steer
    corrected = frames["intervened"]
    assert not np.allclose(frames["applied_action"][corrected], frames["driver_action"][corrected])
    assert not np.allclose(frames["expert"][:, 0], 0.1)  # labelled by the expert, not the driver


def test_steering_noise_is_stationary_and_correlated():
    dt, tau, std = 1.0 / DEFAULT_CONTROL_HZ, 0.5, 0.1
    noise = SteeringNoise(Perturbation(std, tau), dt, seed=0)
    values = np.array([noise.sample() for _ in range(40_000)])
    assert values.std() == pytest.approx(std, rel=0.05)
    lag_one = np.corrcoef(values[:-1], values[1:])[0, 1]
    assert lag_one == pytest.approx(math.exp(-dt / tau), abs=0.02)
    noise.reset()
    assert noise.sample() == values[0]  # seeded: the same episode gets the same noise
    assert SteeringNoise(Perturbation(0.0), dt, seed=0).sample() == 0.0
    with pytest.raises(SafeRaceError, match="steer_std_rad"):
        Perturbation(-0.1)


def test_collect_command_adds_rounds(tmp_path: Path):
    out = tmp_path / "data"
    args = ("collect", "--track", "lab", "--task", "RacingLine", "--max-seconds", "1")
    first = run_cli(*args, "--perturb", "0.05", "--out", str(out))
    assert first.returncode == 0, first.stderr
    assert "round of 20 frames written" in first.stdout
    second = run_cli(*args, "--stereo", "--seeds", "1", "2", "--out", str(out / "stereo"))
    assert second.returncode == 0, second.stderr
    stereo = load_rounds([out / "stereo"])
    assert stereo["image"].shape == (40, 64, 64, 6)
    assert stereo["episode"].tolist() == [0] * 20 + [1] * 20
    bytes_per_frame = (out / "round_0000" / "frames.npz").stat().st_size / 20
    raw_image_bytes = 64 * 64 * 3  # 12 kB uncompressed
    assert bytes_per_frame < 0.5 * raw_image_bytes  # compressed: a frame and its labels
    bad = run_cli(*args, "--perturb", "-0.1", "--out", str(out))
    assert bad.returncode == 2 and "--perturb: must be at least 0" in bad.stderr


def test_a_round_over_two_workers_is_the_serial_round(tmp_path: Path):
    config = CollectionConfig(
        task="CenterLine",
        track="lab",
        seeds=(3, 4),
        episode=EpisodeSettings(laps=1, max_seconds=1.5, randomize="mild"),
    )
    serial = collect_round(tmp_path / "serial", config, progress=False)
    parallel = collect_round(tmp_path / "parallel", config, progress=False, workers=2)
    assert parallel.episodes == serial.episodes
    with np.load(serial.path / "frames.npz") as a, np.load(parallel.path / "frames.npz") as b:
        for name in a.files:
            np.testing.assert_array_equal(a[name], b[name])
        assert set(a["episode"]) == {0, 1}
