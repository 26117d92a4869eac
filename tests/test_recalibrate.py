"""``saferace calibrate``: a conformal calibration fitted on rounds, written into the
checkpoint, and used by every learned state source loaded from it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from saferace.cli import main
from saferace.errors import ConfigError
from saferace.learning.agent import learned_state_source
from saferace.learning.checkpoint import CONFORMAL_KEY, load_checkpoint
from saferace.learning.recalibrate import recalibrate
from saferace.safety.uncertainty.conformal import ConformalCalibration
from saferace.safety.uncertainty.intervals import ConformalStateSource, state_interval


def test_a_calibration_survives_the_checkpoint_round_trip(
    tiny_checkpoint, uncalibrated_checkpoint: Path, tmp_path: Path
):
    checkpoint, data = uncalibrated_checkpoint, tiny_checkpoint()[1]
    out = tmp_path / "calibrated.pt"
    rows = recalibrate(checkpoint, [data], out, alpha=0.1, mc_samples=4, test_share=0.5)
    assert [row["interval"].split(",")[0] for row in rows] == ["its own spread", "conformal"]
    assert all(0.0 <= row["coverage"] <= 1.0 for row in rows)

    original, calibrated = load_checkpoint(checkpoint), load_checkpoint(out)
    assert CONFORMAL_KEY not in original.metadata  # the source checkpoint is left alone
    for name, weights in original.state.state_dict().items():
        assert torch.equal(weights, calibrated.state.state_dict()[name])
    stored = ConformalCalibration.from_dict(calibrated.metadata[CONFORMAL_KEY])
    assert stored.alpha == 0.1 and stored.scale > 0.0 and stored.monitor is not None
    assert ConformalCalibration.from_dict(stored.as_dict()) == stored
    assert calibrated.metadata[CONFORMAL_KEY]["test_coverage"] == rows[-1]["coverage"]

    plain = learned_state_source(checkpoint, (64, 64, 3), n_samples=4, seed=1)
    source = learned_state_source(out, (64, 64, 3), n_samples=4, seed=1)
    assert isinstance(source, ConformalStateSource)
    assert not isinstance(plain, ConformalStateSource)
    samples = np.array([[0.1, 0.0, 0.3], [0.3, 0.2, 0.3], [0.2, 0.1, 0.3]])
    lower, upper = state_interval(source, samples, z=1.0)
    half = stored.scale * samples.std(axis=0)
    assert np.allclose(lower, samples.mean(axis=0) - half)
    assert np.allclose(upper, samples.mean(axis=0) + half)


def test_the_command_prints_the_test_coverage_and_refuses_a_bad_split(
    tiny_checkpoint, tmp_path: Path, capsys
):
    checkpoint, data = tiny_checkpoint()
    out = tmp_path / "cal.pt"
    code = main(["calibrate", str(checkpoint), str(data), "--samples", "3", "--out", str(out)])
    printed = capsys.readouterr().out
    assert code == 0 and out.is_file()
    assert "conformal, mean +-" in printed and "coverage" in printed
    with pytest.raises(ConfigError, match="test_share"):
        recalibrate(checkpoint, [data], tmp_path / "x.pt", test_share=1.0)


def test_an_adaptive_interval_needs_a_calibrated_checkpoint(
    tiny_checkpoint, uncalibrated_checkpoint: Path, tmp_path: Path
):
    import gymnasium as gym

    from saferace.eval.filters import FilterConfig, apply_filter
    from saferace.safety.uncertainty.adaptive import AdaptiveConformalStateSource

    checkpoint, data = uncalibrated_checkpoint, tiny_checkpoint()[1]
    calibrated = tmp_path / "calibrated.pt"
    recalibrate(checkpoint, [data], calibrated, alpha=0.1, mc_samples=3)
    env = gym.make("saferace/CenterLine-v0", track="lab", max_laps=1)
    for path, works in ((calibrated, True), (checkpoint, False)):
        config = FilterConfig(  # chance: the adaptive interval's own check, not the robust one's
            kind="cbf", state_source=f"learned:{path}", samples=3, adaptive="odometry",
            uncertainty="chance",
        )  # fmt: skip
        if works:
            filtered = apply_filter(env, config, seed=0)
            assert isinstance(filtered.state_source, AdaptiveConformalStateSource)
        else:
            with pytest.raises(ConfigError, match="calibrat"):
                apply_filter(env, config, seed=0)
    with pytest.raises(ConfigError, match="adaptive"):
        FilterConfig(kind="cbf", adaptive="oracle")  # the truth needs no adapting
    env.close()


def test_the_fitted_interval_covers_its_calibration_frames_as_promised(tiny_checkpoint):
    """Split conformal's guarantee on the frames it was fitted on: ``mean +- scale * std``
    of the very predictions it scored covers at least ``1 - alpha`` of them, and a scale a
    fifth smaller covers fewer (the quantile is no looser than it must be)."""
    from saferace.learning.calibration import CALIBRATED_OUTPUTS, fit_conformal
    from saferace.learning.rounds import load_rounds
    from saferace.learning.training_data import network_data
    from saferace.learning.validation import predict_frames
    from saferace.safety.uncertainty.conformal import coverage

    checkpoint, data = tiny_checkpoint()
    network, frames = load_checkpoint(checkpoint).state, load_rounds([data])
    alpha = 0.2
    calibration = fit_conformal(network, frames, alpha=alpha, n_samples=3, monitor="none")
    state = network_data(frames)["state"]
    prediction = predict_frames(network, state, n_samples=3)
    lane = slice(0, len(CALIBRATED_OUTPUTS))
    mean, std, truth = prediction.mean[:, lane], prediction.std[:, lane], state.targets[:, lane]

    def covered(scale: float) -> float:
        return coverage(mean - scale * std, mean + scale * std, truth)[0]

    assert covered(calibration.scale) >= 1.0 - alpha
    assert covered(0.8 * calibration.scale) < 1.0 - alpha
