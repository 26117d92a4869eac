"""The deep ensemble of heteroscedastic state networks: its mixture, its training and its
checkpoint."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from saferace.errors import SafeRaceError
from saferace.learning.checkpoint import load_checkpoint, save_checkpoint
from saferace.learning.configs import TrainConfig
from saferace.learning.ensemble import StateEnsemble, mixture
from saferace.learning.networks import DrivingNetwork, state_config
from saferace.learning.rounds import load_rounds
from saferace.learning.training import train_networks


def test_the_mixture_variance_is_the_members_noise_plus_their_disagreement():
    rng = np.random.default_rng(0)
    means = rng.normal(0.0, 1.0, (5, 4, 3))
    stds = rng.uniform(0.1, 0.5, (5, 4, 3))
    mean, std = mixture(means, stds)
    # Draw from the mixture itself: pick a member, then its Gaussian.
    draws = 200_000
    member = rng.integers(0, 5, draws)
    samples = means[member] + stds[member] * rng.standard_normal((draws, 4, 3))
    assert np.allclose(mean, samples.mean(axis=0), atol=0.02)
    assert np.allclose(std, samples.std(axis=0), rtol=0.01)
    # Agreeing members leave their own noise; disagreeing ones add their spread.
    same = mixture(np.zeros((3, 1, 1)), np.full((3, 1, 1), 0.2))[1]
    assert same == pytest.approx(0.2)
    apart = mixture(np.array([-1.0, 1.0]).reshape(2, 1, 1), np.full((2, 1, 1), 0.2))[1]
    assert apart == pytest.approx(np.sqrt(0.04 + 1.0))


def member(seed: int) -> DrivingNetwork:
    torch.manual_seed(seed)
    return DrivingNetwork(state_config(log_variance=True)).eval()


def test_an_ensembles_prediction_and_samples_are_its_members_mixture():
    members = [member(seed) for seed in range(3)]
    ensemble = StateEnsemble(members)
    image = np.random.default_rng(1).integers(0, 255, (2, 64, 64, 3), dtype=np.uint8)
    prediction = ensemble.predict(image)
    alone = [m.predict(image) for m in members]
    mean, std = mixture(np.stack([p.mean for p in alone]), np.stack([p.std for p in alone]))
    assert np.allclose(prediction.mean, mean) and np.allclose(prediction.std, std)
    assert prediction.samples.shape == (2, 6, 3)
    assert np.allclose(prediction.samples.mean(axis=1), mean, atol=1e-6)
    assert np.allclose(prediction.samples.std(axis=1), std, rtol=1e-5)
    with pytest.raises(SafeRaceError, match="heteroscedastic"):
        StateEnsemble([DrivingNetwork(state_config()), DrivingNetwork(state_config())])


def test_an_ensemble_trains_distinct_members_and_survives_a_checkpoint(
    tiny_checkpoint, tmp_path: Path
):
    _, data = tiny_checkpoint()
    config = TrainConfig(
        epochs=1, val_stretch=(0.05, 0.08), state_uncertainty="ensemble", ensemble_members=2
    )
    control, state, metadata = train_networks(load_rounds([data]), config, progress=False)
    assert isinstance(state, StateEnsemble) and len(state.members) == 2
    first, second = (m.output_layer.weight for m in state.members)
    assert not torch.equal(first, second)  # each member from its own seed
    assert set(metadata["history"]) == {"control", "state"}
    assert set(metadata["member_history"]) == {"state_member_1"}
    path = save_checkpoint(tmp_path / "ensemble.pt", control, state, metadata)
    loaded = load_checkpoint(path)
    assert isinstance(loaded.state, StateEnsemble)
    image = np.zeros((64, 64, 3), np.uint8)
    assert np.allclose(loaded.state.predict(image).std, state.predict(image).std)
    with pytest.raises(SafeRaceError, match="state uncertainty"):
        train_networks(
            load_rounds([data]),
            TrainConfig(epochs=1, val_stretch=(0.05, 0.08), init=str(path)),
            progress=False,
        )
