"""The learned agent and state source: observation only, filter hand-over, eval rows, GradCAM."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from cli_helpers import run_cli
from rerun.chunk import RrdReader

import saferace  # noqa: F401  (registers the tasks)
from saferace.errors import SafeRaceError
from saferace.eval.agents import make_agent
from saferace.eval.runner import read_jsonl
from saferace.learning.agent import learned_state_source
from saferace.learning.checkpoint import load_checkpoint
from saferace.learning.gradcam import gradcam_maps
from saferace.names import ROBUST_GAINS
from saferace.safety.decision import NominalAction


class ForbiddenInfo(dict):
    """An ``info`` that raises on any read: what an observation-only driver never touches."""

    def _refuse(self, *args, **kwargs):
        raise AssertionError("the learned driver read info")

    __getitem__ = get = __contains__ = __iter__ = keys = values = items = _refuse


@pytest.fixture
def env():
    environment = gym.make("saferace/CenterLine-v0", track="lab")
    yield environment
    environment.close()


def test_learned_agent_drives_from_the_observation_alone(tiny_checkpoint, env):
    agent = make_agent(f"learned:{tiny_checkpoint()[0]}", env, mc_samples=5)
    observation, _ = env.reset(seed=0)
    action = agent.act(observation, ForbiddenInfo())
    assert isinstance(action, NominalAction)
    assert action.mean.shape == action.std.shape == (2,) and np.all(action.std > 0)
    with pytest.raises(AssertionError, match="read info"):  # the guard does catch a reader
        make_agent("expert", env).act(observation, ForbiddenInfo())
    agent.reset()
    assert np.array_equal(agent.act(observation, ForbiddenInfo()).mean, action.mean)  # seeded


def test_episode_seed_draws_the_dropout_masks(tiny_checkpoint, env):
    observation, _ = env.reset(seed=0)
    spec = f"learned:{tiny_checkpoint()[0]}"
    actions = [
        make_agent(spec, env, mc_samples=5, seed=seed).act(observation, ForbiddenInfo()).mean
        for seed in (1, 1, 2)
    ]
    assert np.array_equal(actions[0], actions[1]) and not np.array_equal(actions[0], actions[2])


def test_learned_agent_turns_target_speed_into_acceleration(tiny_checkpoint, env):
    agent = make_agent(f"learned:{tiny_checkpoint()[0]}", env, mc_samples=1)
    observation, _ = env.reset(seed=0)
    prediction = agent.network.predict(observation["image"], observation["velocity"], 1)
    action = agent.act(observation, ForbiddenInfo())
    steer, target_speed = prediction.mean[0]
    assert action.mean[0] == pytest.approx(steer)
    speed_error = target_speed - observation["velocity"][0]
    gains = agent.speed_controller.gains
    expected = np.clip(
        gains.kp_per_s * speed_error + gains.ki_per_s2 * speed_error * 0.05,
        gains.min_accel_mps2,
        gains.max_accel_mps2,
    )
    assert action.mean[1] == pytest.approx(expected, rel=1e-5)
    assert np.all(action.std == 0.0)  # one sample: no spread


def test_learned_state_source_gives_samples_from_the_image(tiny_checkpoint, env):
    source = learned_state_source(tiny_checkpoint()[0], (64, 64, 3), n_samples=8, seed=3)
    observation, _ = env.reset(seed=0)
    samples = source.samples(observation, ForbiddenInfo())
    assert samples.shape == (8, 3) and samples.std(axis=0).min() > 0
    source.reset(3)
    assert np.array_equal(source.samples(observation, ForbiddenInfo()), samples)


def test_checkpoint_must_match_the_camera(tiny_checkpoint):
    checkpoint = tiny_checkpoint()[0]
    stereo_env = gym.make("saferace/CenterLine-v0", track="lab", stereo=True)
    try:
        with pytest.raises(SafeRaceError, match="drop --stereo"):
            make_agent(f"learned:{checkpoint}", stereo_env)
    finally:
        stereo_env.close()
    with pytest.raises(SafeRaceError, match="trained on images"):
        learned_state_source(checkpoint, (96, 96, 3))  # same channels, another size


def test_eval_rows_record_checkpoint_and_state_source(tiny_checkpoint, tmp_path: Path):
    checkpoint = tiny_checkpoint()[0]
    out = tmp_path / "rows.jsonl"
    result = run_cli(
        "eval", "--agent", f"learned:{checkpoint}", "--task", "CenterLine", "--track", "lab",
        "--filter", "cbf", "--state-source", f"learned:{checkpoint}", "--samples", "3",
        "--mc-samples", "4", "--spread-scale", "3", "2", "1", "--filter-uncertainty", "chance",
        "--max-seconds", "1", "--out", str(out),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    (row,) = read_jsonl(out)
    sha = load_checkpoint(checkpoint).sha256
    assert row["agent_checkpoint"] == {"path": str(checkpoint), "sha256": sha, "mc_samples": 4}
    recorded = {
        "path": str(checkpoint),
        "sha256": sha,
        "mc_samples": 3,
        "spread_scale": [3.0, 2.0, 1.0],
    }
    assert {name: row["state_source"][name] for name in recorded} == recorded
    assert row["state_source"]["conformal"]["alpha"] == 0.05  # the checkpoint's calibration
    assert row["filter"]["state_source"] == f"learned:{checkpoint}"
    assert row["summary"]["intervention_rate"] is not None
    refused = run_cli(
        "eval", "--state-source", f"learned:{checkpoint}", "--out", str(tmp_path / "x.jsonl")
    )
    assert refused.returncode == 2 and "--filter cbf" in refused.stderr


@pytest.mark.slow  # 15-30 s: the default suite stays within 15 min on 2 cores
def test_the_default_filter_refuses_an_uncalibrated_state_network(
    tiny_checkpoint, uncalibrated_checkpoint: Path, tmp_path: Path
):
    checkpoint, uncalibrated = tiny_checkpoint()[0], uncalibrated_checkpoint
    out = tmp_path / "rows.jsonl"
    command = ("eval", "--track", "lab", "--max-seconds", "0.5", "--out", str(out), "--samples",
               "3", "--filter", "cbf", "--state-source")  # fmt: skip
    refused = run_cli(*command, f"learned:{uncalibrated}")
    assert refused.returncode == 2
    assert f"saferace calibrate {uncalibrated}" in refused.stderr, refused.stderr
    assert "--filter-uncertainty chance" in refused.stderr
    for source, mode in ((uncalibrated, "chance"), (checkpoint, "auto")):
        taken = run_cli(*command, f"learned:{source}", "--filter-uncertainty", mode)
        assert taken.returncode == 0, taken.stderr
    paper, robust = (row["filter"] for row in read_jsonl(out))
    assert (paper["uncertainty"], paper["gains"]) == ("chance", "grip")
    assert (robust["uncertainty"], robust["gains"]) == ("robust", ROBUST_GAINS)


@pytest.mark.parametrize(
    "stereo",
    # the stereo checkpoint's training and maps: 15 s, so in the slow suite (its network's
    # two cameras are checked in tests/test_networks.py)
    [False, pytest.param(True, marks=pytest.mark.slow)],
)
def test_gradcam_maps_and_command(tiny_checkpoint, tmp_path: Path, stereo: bool):
    checkpoint = tiny_checkpoint(stereo)[0]
    loaded = load_checkpoint(checkpoint)
    image = np.random.default_rng(0).integers(0, 256, (64, 64, 6 if stereo else 3), np.uint8)
    maps = gradcam_maps(loaded.state, image, None, "layer2")
    assert maps.shape == (3, 64, 64)
    peaks = maps.max(axis=(1, 2))  # each map normalised, or empty: no positive evidence
    assert maps.min() >= 0.0 and np.all(np.isclose(peaks, 1.0) | (peaks == 0.0))
    assert np.isclose(peaks, 1.0).any()
    result = run_cli("gradcam", str(checkpoint), "--frames", "2", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    sheets = sorted(tmp_path.glob("gradcam_*.png"))
    assert len(sheets) == 2
    import cv2

    height = cv2.imread(str(sheets[0])).shape[0]
    assert height == 18 + (2 if stereo else 1) * 64 * 3  # titles, then one row per camera


def test_drive_records_what_the_filter_believed(tiny_checkpoint, tmp_path: Path):
    checkpoint = tiny_checkpoint()[0]
    recording = tmp_path / "filtered.rrd"
    result = run_cli(
        "drive", "--agent", f"learned:{checkpoint}", "--task", "CenterLine", "--track", "lab",
        "--filter", "cbf", "--state-source", f"learned:{checkpoint}", "--samples", "3",
        "--rerun", str(recording),
    )  # fmt: skip
    assert result.returncode in (0, 1), result.stderr  # 1: the tiny network missed the lap
    entities = {str(path) for path in RrdReader(recording).store().schema().entity_paths()}
    for entity in (
        "/filter/e_y_m/true",
        "/filter/e_y_m/believed",
        "/filter/e_y_m/believed_plus_2sd",
        "/filter/steer_rad/nominal",
        "/filter/steer_rad/filtered",
        "/filter/barriers/lane_left",
        "/camera/onboard",
    ):
        assert entity in entities, entity
