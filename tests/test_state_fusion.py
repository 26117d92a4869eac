"""The odometry-fused state source: it tracks the truth, and a confident wrong network
cannot drag it away."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from cli_helpers import run_cli

import saferace  # noqa: F401  (registers the tasks)
from saferace.agents.pure_pursuit import PurePursuit
from saferace.eval.filters import FilterConfig, apply_filter
from saferace.safety.state_fusion import OdometryFusedStateSource
from saferace.safety.state_sources import NoisyOracleStateSource, true_lane_state


class BiasedSource:
    """A noisy oracle that, from step ``start`` to ``stop``, is off by ``bias`` and sure of it
    (its samples spread 1 cm / 0.01 rad): a network on frames it never saw."""

    def __init__(self, bias: tuple[float, float], start: int, stop: int) -> None:
        self.inner = NoisyOracleStateSource((0.03, 0.03, 0.0), 10, seed=0)
        self.bias = np.array([*bias, 0.0])
        self.start, self.stop = start, stop
        self.step = 0

    def reset(self, seed: int | None = None) -> None:
        self.inner.reset(seed)
        self.step = 0

    def samples(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        self.step += 1
        samples = self.inner.samples(observation, info)
        if self.start <= self.step < self.stop:
            centre = true_lane_state(info) + self.bias
            return centre + (samples - samples.mean(axis=0)) / 3.0
        return samples


def drive(
    source_of, steps: int = 120, **settings
) -> tuple[np.ndarray, np.ndarray, OdometryFusedStateSource]:
    """Pure pursuit round ``lab``; the fused and the true ``[e_y, e_psi]`` at each step."""
    env = gym.make("saferace/CenterLine-v0", track="lab", max_laps=1)
    base = env.unwrapped
    fused = OdometryFusedStateSource(source_of(), base.track, base.control_dt_s, **settings)
    agent = PurePursuit.for_env(env)
    observation, info = env.reset(seed=0)
    fused.reset(0)
    estimates, truths = [], []
    for _ in range(steps):
        estimates.append(fused.samples(observation, info)[:, :2].mean(axis=0))
        truths.append(true_lane_state(info)[:2])
        observation, _, terminated, truncated, info = env.step(agent.act(observation, info))
        assert not (terminated or truncated)
    env.close()
    return np.array(estimates), np.array(truths), fused


def test_fused_state_tracks_the_truth_from_a_noisy_source():
    estimates, truths, fused = drive(lambda: NoisyOracleStateSource((0.05, 0.05, 0.0), 10, seed=0))
    errors = np.abs(estimates - truths)
    assert errors[10:].mean(axis=0) == pytest.approx([0.0, 0.0], abs=0.025)
    assert errors[10:].max(axis=0).tolist() < [0.08, 0.1]
    assert fused.gated < 5  # an honest source is hardly ever gated


def test_a_confident_wrong_source_is_gated_and_odometry_carries_the_state():
    """0.3 rad and 0.2 m off for 0.75 s, with a spread of 1 cm: the fused state keeps to the
    truth within the error it had before, where the source is off by the full bias."""
    start, stop = 60, 75
    during = slice(start, stop)
    estimates, truths, fused = drive(lambda: BiasedSource((0.2, 0.3), start, stop))
    assert fused.gated >= stop - start - 2
    heading_error = np.abs(estimates[during, 1] - truths[during, 1]).max()
    assert np.abs(estimates[during, 0] - truths[during, 0]).max() < 0.08 and heading_error < 0.1
    # After the source is right again, it is taken back at once.
    assert np.abs(estimates[stop + 5 :] - truths[stop + 5 :]).max(axis=0).tolist() < [0.08, 0.1]
    # Without the gate the same source drags the estimate off.
    ungated, truths, fused = drive(lambda: BiasedSource((0.2, 0.3), start, stop), gate_chi2=1e9)
    assert fused.gated == 0
    assert np.abs(ungated[during, 1] - truths[during, 1]).max() > 2 * heading_error


def test_filter_config_fuses_the_source_it_builds():
    env = apply_filter(
        gym.make("saferace/CenterLine-v0", track="lab", max_laps=1),
        FilterConfig(kind="cbf", state_noise=(0.05, 0.05), samples=10, fuse_odometry=True),
        seed=0,
    )
    assert isinstance(env.state_source, OdometryFusedStateSource)
    assert isinstance(env.state_source.source, NoisyOracleStateSource)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([0.0, 0.0]))
    assert info["safety"]["n_samples"] == 10
    env.close()


def test_bad_settings_are_refused():
    env = gym.make("saferace/CenterLine-v0", track="lab")
    base = env.unwrapped
    source = NoisyOracleStateSource()
    with pytest.raises(ValueError, match="positive"):
        OdometryFusedStateSource(source, base.track, 0.0)
    with pytest.raises(ValueError, match="positive"):
        OdometryFusedStateSource(source, base.track, 0.05, process_std=(0.0, 0.02))
    env.close()


def test_the_command_line_fuses_only_a_filtered_uncertain_source(tmp_path):
    drive = ("drive", "--track", "lab", "--laps", "1", "--agent", "pure-pursuit")
    refused = [
        run_cli(*drive, "--fuse-odometry"),
        run_cli(*drive, "--filter", "cbf", "--fuse-odometry"),
        run_cli("dagger", "--iterations", "1", "--fuse-odometry", "--out", str(tmp_path)),
    ]
    for result, reason in zip(
        refused, ("need --filter cbf", "fuses a noisy", "fuses the state"), strict=True
    ):
        assert result.returncode != 0 and reason in result.stderr, result.stderr
