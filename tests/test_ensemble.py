"""The deep and the MIMO ensemble of heteroscedastic state networks: their mixture, their
training and their checkpoint."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from saferace.errors import SafeRaceError
from saferace.learning.checkpoint import load_checkpoint, save_checkpoint
from saferace.learning.configs import TrainConfig
from saferace.learning.ensemble import StateEnsemble
from saferace.learning.networks import DrivingNetwork, mixture, state_config
from saferace.learning.rounds import load_rounds
from saferace.learning.training import (
    MIMO_INPUT_REPETITION,
    epoch_order,
    train_networks,
    training_loss,
)
from saferace.learning.training_data import NetworkData, network_outputs


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


def mimo(subnetworks: int, seed: int = 0) -> DrivingNetwork:
    torch.manual_seed(seed)
    config = state_config(dropout=0.0, log_variance=True, subnetworks=subnetworks)
    network = DrivingNetwork(config)
    network.set_normalisation({"output_mean": [0.1, -0.2, 0.3], "output_std": [0.2, 0.5, 2.0]})
    return network.eval()


def test_mimo_subnetworks_share_a_frame_at_the_input_repetition_rate_else_their_own():
    order = epoch_order(4000, 3, torch.Generator().manual_seed(0))
    assert sorted(order[0]) == list(range(4000))
    shared = (order[1] == order[0]) & (order[2] == order[0])
    assert abs(shared.mean() - MIMO_INPUT_REPETITION) < 0.03  # 4 standard errors
    for other in order[1:, ~shared]:  # elsewhere each draws its own, uniformly
        assert np.mean(other == order[0, ~shared]) < 0.01
        assert 0.45 < np.mean(other < 2000) < 0.55


def test_a_mimo_networks_prediction_is_its_subnetworks_mixture_on_one_frame():
    network = mimo(3)
    image = np.random.default_rng(1).integers(0, 255, (2, 64, 64, 3), dtype=np.uint8)
    prediction = network.predict(image)
    with torch.inference_mode():
        tiled = network(torch.from_numpy(np.concatenate([image] * 3, axis=-1)))
        assert torch.equal(tiled, network(torch.from_numpy(image)))  # every one sees the frame
    per_subnetwork = tiled.reshape(2, 3, 6).numpy()
    std = network.output_std.numpy()
    means = per_subnetwork[..., :3] * std + network.output_mean.numpy()
    stds = np.exp(0.5 * per_subnetwork[..., 3:]) * std
    mean, spread = mixture(means.transpose(1, 0, 2), stds.transpose(1, 0, 2))
    assert np.allclose(prediction.mean, mean, atol=1e-6)
    assert np.allclose(prediction.std, spread, rtol=1e-5)
    assert prediction.samples.shape == (2, 6, 3) and prediction.features.shape == (2, 512)
    assert np.allclose(prediction.samples.mean(axis=1), mean, atol=1e-6)
    assert np.allclose(prediction.samples.std(axis=1), spread, rtol=1e-5)
    assert np.ptp(means, axis=1).min() > 0.0  # the subnetworks disagree
    with pytest.raises(SafeRaceError, match="heteroscedastic"):
        state_config(subnetworks=2)


def test_each_mimo_subnetwork_is_scored_on_its_own_frames():
    network = mimo(2)
    targets = torch.tensor([[[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]] * 4)  # (B, K, outputs)
    exact = torch.cat([targets[:, 0], torch.zeros(4, 3), targets[:, 1], torch.zeros(4, 3)], 1)
    swapped = torch.cat([targets[:, 1], torch.zeros(4, 3), targets[:, 0], torch.zeros(4, 3)], 1)
    assert float(training_loss(network, exact, targets)) == pytest.approx(0.0)
    assert float(training_loss(network, swapped, targets)) == pytest.approx(0.5 * 9.0)


def test_a_mimo_batch_gives_each_subnetwork_its_own_frames_in_its_channels():
    images = np.arange(6, dtype=np.uint8)[:, None, None, None] * np.ones((1, 4, 4, 3), np.uint8)
    data = NetworkData(images, None, np.zeros((6, 3), np.float32))
    order = epoch_order(6, 2, torch.Generator().manual_seed(0))
    assert order.shape == (2, 6) and sorted(order[0]) == list(range(6))
    index = np.array([[0, 1, 2, 3], [5, 1, 4, 0]])
    batch = network_outputs(lambda images, velocity: images, data, index)
    assert batch.shape == (4, 4, 4, 6)
    for subnetwork in range(2):
        seen = batch[:, 0, 0, 3 * subnetwork : 3 * (subnetwork + 1)]
        assert torch.equal(seen, torch.from_numpy(index[subnetwork])[:, None].expand(4, 3).byte())


def test_a_mimo_ensemble_trains_and_survives_a_checkpoint(tiny_checkpoint, tmp_path: Path):
    _, data = tiny_checkpoint()
    config = TrainConfig(
        epochs=1, val_stretch=(0.05, 0.08), state_uncertainty="mimo", ensemble_members=3
    )
    control, state, metadata = train_networks(load_rounds([data]), config, progress=False)
    assert isinstance(state, DrivingNetwork) and state.config.subnetworks == 3
    assert set(metadata["history"]) == {"control", "state"} and not metadata["member_history"]
    path = save_checkpoint(tmp_path / "mimo.pt", control, state, metadata)
    loaded = load_checkpoint(path)
    image = np.full((64, 64, 3), 90, np.uint8)
    assert loaded.state.config == state.config
    assert np.array_equal(loaded.state.predict(image).std, state.predict(image).std)
    assert np.ptp(loaded.state.predict(image).samples[0, :3, 0]) > 0.0  # distinct subnetworks
