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
from saferace.safety.uncertainty.state_fusion import OdometryFusedStateSource, frenet_step
from saferace.safety.uncertainty.state_sources import NoisyOracleStateSource, true_lane_state
from tests.test_dead_reckoning import lane_state_on_circle, on_circle


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
    source_of, steps: int = 120, gyro_bias: tuple[int, int, float] = (0, 0, 0.0), **settings
) -> tuple[np.ndarray, np.ndarray, OdometryFusedStateSource]:
    """Pure pursuit round ``lab``; the fused and the true ``[e_y, e_psi]`` at each step. The
    fused source's yaw rate is off by ``bias`` rad/s from step ``start`` to ``stop``."""
    env = gym.make("saferace/CenterLine-v0", track="lab", max_laps=1)
    base = env.unwrapped
    fused = OdometryFusedStateSource(source_of(), base.track, base.control_dt_s, **settings)
    agent = PurePursuit.for_env(env)
    observation, info = env.reset(seed=0)
    fused.reset(0)
    start, stop, bias = gyro_bias
    estimates, truths = [], []
    for step in range(steps):
        velocity = observation["velocity"] + np.array([0.0, 0.0, bias * (start <= step < stop)])
        seen = {**observation, "velocity": velocity}
        estimates.append(fused.samples(seen, info)[:, :2].mean(axis=0))
        truths.append(true_lane_state(info)[:2])
        observation, _, terminated, truncated, info = env.step(agent.act(observation, info))
        assert not (terminated or truncated)
    env.close()
    return np.array(estimates), np.array(truths), fused


def test_fused_state_tracks_the_truth_from_a_noisy_source():
    estimates, truths, fused = drive(lambda: NoisyOracleStateSource((0.05, 0.05, 0.0), 10, seed=0))
    errors = np.abs(estimates - truths)
    assert errors[10:].mean(axis=0) == pytest.approx([0.0, 0.0], abs=0.025)
    assert np.all(errors[10:].max(axis=0) < [0.08, 0.1])
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
    assert np.all(np.abs(estimates[stop + 5 :] - truths[stop + 5 :]).max(axis=0) < [0.08, 0.1])
    # Without the gate the same source drags the estimate off.
    ungated, truths, fused = drive(lambda: BiasedSource((0.2, 0.3), start, stop), gate_chi2=1e9)
    assert fused.gated == 0
    assert np.abs(ungated[during, 1] - truths[during, 1]).max() > 2 * heading_error


def test_after_a_gyro_fault_the_source_is_taken_back():
    """Odometry is trusted over the source for ``max_gated_steps`` steps, not for ever: with
    a yaw rate 2 rad/s off for 1.5 s, the dead-reckoned heading runs away, the honest source
    is gated, and then taken back (1 s after the fault); trusting odometry for ever, the
    estimate stays lost."""
    fault = (40, 70, 2.0)
    honest = lambda: NoisyOracleStateSource((0.03, 0.03, 0.0), 10, seed=0)  # noqa: E731
    estimates, truths, fused = drive(honest, gyro_bias=fault)
    assert fused.gated >= fused.max_gated_steps
    assert np.all(np.abs(estimates[90:] - truths[90:]).max(axis=0) < [0.08, 0.1])
    stubborn, truths, _ = drive(honest, gyro_bias=fault, max_gated_steps=10**6)
    assert np.abs(stubborn[90:, 1] - truths[90:, 1]).min() > 0.3


def test_frenet_step_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    for _ in range(20):
        state = np.array([rng.uniform(-0.4, 0.4), rng.uniform(-0.5, 0.5)])
        velocity = np.array([rng.uniform(0.5, 7.0), rng.uniform(-0.4, 0.4), rng.uniform(-2, 2)])
        kappa = rng.uniform(-1.0, 1.0)
        _, jacobian = frenet_step(state, velocity, kappa, 0.05)
        numeric = np.column_stack(
            [
                (frenet_step(state + step, velocity, kappa, 0.05)[0]
                 - frenet_step(state - step, velocity, kappa, 0.05)[0]) / 2e-6
                for step in np.eye(2) * 1e-6
            ]
        )  # fmt: skip
        np.testing.assert_allclose(jacobian, numeric, atol=1e-6)


def test_a_frenet_step_round_a_circle_is_where_the_car_goes_to_first_order():
    """On the 2 m circle of ``tests/test_dead_reckoning.py`` (curvature 0.5), a car 0.3 m
    inside at 0.2 rad, moving at ``[3, 0.1, 1.0]``: over 1 ms the step lands within 1e-5 of
    where polar geometry puts the car (a first-order step's error; a wrong sign or term is
    off by about 1e-3)."""
    e_y0, e_psi0, (v_x, v_y, yaw_rate), dt = 0.3, 0.2, (3.0, 0.1, 1.0), 1e-3
    centre = on_circle(0.0)
    x, y = centre[:2] + e_y0 * np.array([-np.sin(centre[2]), np.cos(centre[2])])
    yaw = centre[2] + e_psi0
    for _ in range(1000):  # the body's motion, integrated finely
        h = dt / 1000
        x += h * (v_x * np.cos(yaw) - v_y * np.sin(yaw))
        y += h * (v_x * np.sin(yaw) + v_y * np.cos(yaw))
        yaw += h * yaw_rate
    e_y1, e_psi1, _ = lane_state_on_circle(np.array([x, y, yaw]))
    moved, _ = frenet_step(np.array([e_y0, e_psi0]), np.array([v_x, v_y, yaw_rate]), 0.5, dt)
    np.testing.assert_allclose(moved, [e_y1, e_psi1], atol=1e-5)


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


def test_fusing_the_truth_is_refused_and_fused_runs_are_told_apart():
    with pytest.raises(ValueError, match="not the truth"):
        FilterConfig(kind="cbf", fuse_odometry=True)
    noisy = FilterConfig(kind="cbf", state_noise=(0.05, 0.05))
    fused = FilterConfig(kind="cbf", state_noise=(0.05, 0.05), fuse_odometry=True)
    assert (noisy.label, fused.label) == ("noisy-prob", "noisy-fused-prob")


def test_bad_settings_are_refused():
    env = gym.make("saferace/CenterLine-v0", track="lab")
    base = env.unwrapped
    source = NoisyOracleStateSource()
    with pytest.raises(ValueError, match="positive"):
        OdometryFusedStateSource(source, base.track, 0.0)
    with pytest.raises(ValueError, match="positive"):
        OdometryFusedStateSource(source, base.track, 0.05, process_std=(0.0, 0.02))
    env.close()


@pytest.mark.slow  # 15-30 s: the default suite stays within 15 min on 2 cores
def test_the_command_line_fuses_only_a_filtered_uncertain_source(tmp_path):
    drive = ("drive", "--track", "lab", "--laps", "1", "--agent", "pure-pursuit")
    refused = [
        run_cli(*drive, "--fuse-odometry"),
        run_cli(*drive, "--filter", "cbf", "--fuse-odometry"),
        run_cli("dagger", "--iterations", "1", "--fuse-odometry", "--out", str(tmp_path)),
    ]
    for result, reason in zip(
        refused, ("need --filter cbf", "fuses a noisy", "fuses a state network"), strict=True
    ):
        assert result.returncode != 0 and reason in result.stderr, result.stderr
