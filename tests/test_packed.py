"""Packed ensembles: independent members in grouped layers, trained and predicted at once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from saferace.errors import SafeRaceError
from saferace.learning.checkpoint import load_checkpoint, save_checkpoint
from saferace.learning.configs import TrainConfig
from saferace.learning.networks import DrivingNetwork, mixture, state_config
from saferace.learning.packed import GroupedLinear, PackedResNet18, check_packing, packed_width
from saferace.learning.rounds import load_rounds
from saferace.learning.training import train_networks, training_loss

MEMBERS = 3


def packed(seed: int = 0, members: int = MEMBERS, alpha: float = 1.0) -> DrivingNetwork:
    torch.manual_seed(seed)
    network = DrivingNetwork(state_config(0.0, log_variance=True, packed=(members, alpha, 1)))
    network.set_normalisation({"output_mean": [0.1, -0.2, 0.3], "output_std": [0.2, 0.5, 2.0]})
    return network.eval()


def member_points(network: DrivingNetwork, image: np.ndarray) -> np.ndarray:
    """Each member's two samples ``mean_k -+ std_k``: ``(members, N, 2, outputs)``."""
    samples = network.predict(image).samples
    members = network.config.members
    return np.stack([samples[:, [k, members + k]] for k in range(members)])


def perturb_member(network: DrivingNetwork, member: int) -> None:
    """Add noise to every weight member ``member`` owns, in every layer."""
    generator = torch.Generator().manual_seed(7)
    with torch.no_grad():
        for module in network.modules():
            if isinstance(module, nn.Conv2d | nn.BatchNorm2d):
                block = module.weight.shape[0] // network.config.members
                owned = module.weight[member * block : (member + 1) * block]
            elif isinstance(module, GroupedLinear):
                owned = module.weight[member]
            else:
                continue
            owned += 0.3 * torch.randn(owned.shape, generator=generator)


def test_changing_one_packed_members_weights_changes_only_its_outputs():
    network = packed()
    image = np.random.default_rng(1).integers(0, 255, (2, 64, 64, 3), dtype=np.uint8)
    before = member_points(network, image)
    perturb_member(network, 1)
    after = member_points(network, image)
    assert not np.allclose(after[1], before[1], atol=1e-3)
    assert np.array_equal(after[0], before[0]) and np.array_equal(after[2], before[2])


def test_a_packed_prediction_is_its_members_mixture_and_their_features():
    network = packed()
    image = np.random.default_rng(2).integers(0, 255, (2, 64, 64, 3), dtype=np.uint8)
    prediction = network.predict(image)
    points = member_points(network, image)
    means, stds = points.mean(axis=2), np.abs(np.diff(points, axis=2)[:, :, 0]) / 2
    mean, std = mixture(means, stds)
    assert np.allclose(prediction.mean, mean, atol=1e-5)
    assert np.allclose(prediction.std, std, rtol=1e-4)
    assert np.ptp(means, axis=0).min() > 0.0  # the members disagree
    width = packed_width(512, MEMBERS, 1.0, 1)
    assert prediction.features.shape == (2, width) and width % MEMBERS == 0


def test_packed_widths_are_alpha_times_resnets_in_whole_groups_and_cost_about_one_network():
    assert packed_width(64, 5, 2.0, 1) == 130 and packed_width(64, 5, 2.0, 2) == 130
    assert packed_width(512, 4, 1.0, 2) == 512
    backbone = PackedResNet18(3, 5, 2.0, 1)
    convolutions = [m for m in backbone.modules() if isinstance(m, nn.Conv2d)]
    assert convolutions[0].groups == 1 and all(m.groups == 5 for m in convolutions[1:])
    resnet = DrivingNetwork(state_config(log_variance=True)).backbone
    weights = sum(p.numel() for p in backbone.parameters())
    assert 0.6 < weights / sum(p.numel() for p in resnet.parameters()) < 1.0
    with pytest.raises(SafeRaceError, match="2 members"):
        check_packing(1, 2.0, 1)
    for alpha, gamma, match in ((0.0, 1, "alpha"), (2.0, 0, "gamma")):
        with pytest.raises(SafeRaceError, match=match):
            state_config(log_variance=True, packed=(3, alpha, gamma))
    with pytest.raises(SafeRaceError, match="heteroscedastic"):
        state_config(packed=(3, 2.0, 1))


def test_every_packed_member_is_scored_on_the_same_frame():
    network = packed()
    targets = torch.tensor([[0.0, 1.0, 2.0]] * 4)
    exact = torch.cat([targets, torch.zeros(4, 3)] * MEMBERS, 1)
    one_off = exact.clone()
    one_off[:, 6:9] += 3.0  # the second member's means, 3 off
    assert float(training_loss(network, exact, targets)) == pytest.approx(0.0)
    assert float(training_loss(network, one_off, targets)) == pytest.approx(0.5 * 9.0 / MEMBERS)


def test_a_packed_ensemble_trains_and_survives_a_checkpoint(tiny_checkpoint, tmp_path: Path):
    _, data = tiny_checkpoint()
    config = TrainConfig(
        epochs=1,
        val_stretch=(0.05, 0.08),
        state_uncertainty="packed",
        ensemble_members=MEMBERS,
        packed_alpha=1.0,
        packed_gamma=2,
    )
    control, state, metadata = train_networks(load_rounds([data]), config, progress=False)
    assert isinstance(state, DrivingNetwork)
    assert (state.config.packed, state.config.alpha, state.config.gamma) == (MEMBERS, 1.0, 2)
    assert set(metadata["history"]) == {"control", "state"} and not metadata["member_history"]
    path = save_checkpoint(tmp_path / "packed.pt", control, state, metadata)
    loaded = load_checkpoint(path)
    image = np.full((64, 64, 3), 90, np.uint8)
    assert loaded.state.config == state.config
    assert np.array_equal(loaded.state.predict(image).samples, state.predict(image).samples)
    assert np.ptp(member_points(state, image)[:, 0, 0].mean(axis=-1)) > 0.0  # distinct members
