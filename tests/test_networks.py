"""The control and state networks: shapes, MC dropout, normalisation, torchvision weights."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torchvision

from saferace.errors import SafeRaceError
from saferace.learning.networks import (
    CONTROL_OUTPUTS,
    STATE_OUTPUTS,
    DrivingNetwork,
    control_config,
    load_torchvision_weights,
    state_config,
)

SIZE = 32


def network(kind: str, stereo: bool = False, dropout: float = 0.2, seed: int = 0):
    torch.manual_seed(seed)
    make = control_config if kind == "control" else state_config
    return DrivingNetwork(make(stereo, dropout)).eval()


def images(count: int, channels: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (count, SIZE, SIZE, channels), np.uint8)


VELOCITY = np.array([[3.0, 0.1, 0.5], [2.0, -0.1, -0.3]], np.float32)


@pytest.mark.parametrize("stereo", [False, True])
def test_shapes_for_mono_and_stereo(stereo: bool):
    channels = 6 if stereo else 3
    control, state = network("control", stereo), network("state", stereo)
    batch = images(2, channels)
    assert control(torch.from_numpy(batch), torch.from_numpy(VELOCITY)).shape == (2, 2)
    assert state(torch.from_numpy(batch)).shape == (2, 3)
    prediction = control.predict(batch, VELOCITY, n_samples=7)
    assert prediction.mean.shape == prediction.std.shape == (2, len(CONTROL_OUTPUTS))
    assert prediction.samples.shape == (2, 7, len(CONTROL_OUTPUTS))
    single = state.predict(batch[0], n_samples=5)  # one (H, W, C) frame
    assert single.samples.shape == (1, 5, len(STATE_OUTPUTS))
    with pytest.raises(SafeRaceError, match="expected images"):
        state.predict(images(1, 9 - channels))


def test_mc_spread_with_dropout_and_none_without():
    batch = images(2, 3)
    with_dropout = network("control").predict(batch, VELOCITY, n_samples=10)
    assert np.all(with_dropout.std > 0.0)
    assert with_dropout.std == pytest.approx(with_dropout.samples.std(axis=1), rel=1e-5)
    one_sample = network("control").predict(batch, VELOCITY, n_samples=1)
    assert np.all(one_sample.std == 0.0)
    no_dropout = network("control", dropout=0.0).predict(batch, VELOCITY, n_samples=10)
    assert np.all(no_dropout.std == 0.0)


def test_backbone_runs_once_and_the_head_once_per_sample():
    control = network("control")
    calls = {"backbone": [], "head": []}
    control.backbone.register_forward_hook(lambda m, i, o: calls["backbone"].append(len(i[0])))
    control.output_layer.register_forward_hook(lambda m, i, o: calls["head"].append(len(i[0])))
    control.predict(images(3, 3), np.repeat(VELOCITY[:1], 3, axis=0), n_samples=10)
    assert calls == {"backbone": [3], "head": [30]}  # one batch of 3 frames x 10 samples


def test_seeded_samples_repeat():
    control = network("control")
    batch = images(2, 3)
    first = control.predict(batch, VELOCITY, 10, torch.Generator().manual_seed(4))
    again = control.predict(batch, VELOCITY, 10, torch.Generator().manual_seed(4))
    other = control.predict(batch, VELOCITY, 10, torch.Generator().manual_seed(5))
    assert np.array_equal(first.samples, again.samples)
    assert not np.array_equal(first.samples, other.samples)


def test_normalisation_round_trip_and_physical_outputs():
    state = network("state")
    output_mean, output_std = np.array([0.1, -0.2, 0.5]), np.array([0.3, 0.05, 0.8])
    state.set_normalisation({"output_mean": output_mean, "output_std": output_std})
    values = torch.tensor([[0.4, 0.0, -1.0], [-0.2, 0.1, 2.0]])
    round_trip = state.denormalise_outputs(state.normalise_outputs(values))
    assert torch.allclose(round_trip, values, atol=1e-6)
    with torch.no_grad():  # a head that outputs 0 predicts the training data's mean
        state.output_layer.weight.zero_()
        state.output_layer.bias.zero_()
    prediction = state.predict(images(2, 3), n_samples=4)
    assert prediction.mean == pytest.approx(np.tile(output_mean, (2, 1)), abs=1e-6)
    assert np.all(prediction.std == 0.0)


def test_predict_refuses_training_mode():
    state = network("state").train()
    with pytest.raises(SafeRaceError, match="eval"):
        state.predict(images(1, 3))


def test_torchvision_weights_load_and_adapt_to_stereo(tmp_path: Path):
    torch.manual_seed(3)
    source = torchvision.models.resnet18(weights=None)
    path = tmp_path / "resnet18.pth"
    torch.save(source.state_dict(), path)
    mono, stereo = network("state"), network("state", stereo=True, seed=1)
    load_torchvision_weights(mono, path)
    load_torchvision_weights(stereo, path)
    assert torch.equal(mono.backbone.conv1.weight, source.conv1.weight)
    assert torch.equal(mono.backbone.layer4[1].conv2.weight, source.layer4[1].conv2.weight)
    stacked = torch.cat([source.conv1.weight, source.conv1.weight], dim=1) / 2
    assert torch.equal(stereo.backbone.conv1.weight, stacked)
    # A stereo pair of two identical images gives the mono network's features.
    mono_image = images(2, 3)
    pair = np.concatenate([mono_image, mono_image], axis=-1)
    stereo.set_normalisation({"image_mean": [0.5] * 6, "image_std": [0.25] * 6})
    with torch.no_grad():
        mono_features = mono.features(torch.from_numpy(mono_image))
        stereo_features = stereo.features(torch.from_numpy(pair))
    assert torch.allclose(mono_features, stereo_features, atol=1e-4)


def test_torchvision_weights_errors(tmp_path: Path):
    not_weights = tmp_path / "other.pth"
    torch.save({"something": torch.zeros(1)}, not_weights)
    with pytest.raises(SafeRaceError, match="not a torchvision ResNet-18"):
        load_torchvision_weights(network("state"), not_weights)
    with pytest.raises(SafeRaceError, match="cannot read"):
        load_torchvision_weights(network("state"), tmp_path / "missing.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a state dict")
    with pytest.raises(SafeRaceError, match="cannot read"):
        load_torchvision_weights(network("state"), tmp_path / "junk.pth")
