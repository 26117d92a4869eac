"""Training: it learns, it is deterministic, checkpoints round-trip, the commands write reports."""

from __future__ import annotations

import copy
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from cli_helpers import run_cli

from saferace.errors import SafeRaceError
from saferace.learning import training
from saferace.learning.augmentation import photometric
from saferace.learning.checkpoint import load_checkpoint, save_checkpoint
from saferace.learning.networks import DrivingNetwork, state_config
from saferace.learning.rounds import load_rounds
from saferace.learning.training import TrainConfig, fit, normalisation, train_networks
from saferace.learning.training_data import NetworkData, held_out_mask, network_data

FEW = TrainConfig(epochs=1, batch_size=8, val_stretch=(0.05, 0.08))


@pytest.fixture(scope="module")
def frames(tiny_checkpoint):
    return load_rounds([tiny_checkpoint()[1]])


def state_network_for(data) -> DrivingNetwork:
    """An untrained state network normalised for ``data``."""
    network = DrivingNetwork(state_config())
    network.set_normalisation(normalisation(data, seed=0))
    return network


def test_overfits_a_tiny_dataset(frames):
    data = network_data(frames.subset(np.arange(16)))["state"]
    torch.manual_seed(0)
    network = state_network_for(data)
    config = TrainConfig(epochs=30, batch_size=8)
    history = fit(network, data, None, config, "state", progress=False)
    assert history["train_loss"][-1] < history["train_loss"][0] / 10.0


def test_few_frames_train_for_at_least_min_steps(frames):
    data = network_data(frames.subset(np.arange(20)))["state"]  # 3 batches of 8
    network = state_network_for(data)
    config = TrainConfig(epochs=1, batch_size=8, min_steps=7)
    history = fit(network, data, None, config, "state", progress=False)
    assert len(history["train_loss"]) == 3  # ceil(7 / 3) epochs
    assert len(history["batch_loss"]) == 9
    assert replace(config, epochs=4).steps_for(20) == 12  # enough steps already
    with pytest.raises(SafeRaceError, match="min_steps"):
        TrainConfig(min_steps=-1)


def test_max_steps_cuts_the_last_epoch_short(frames):
    data = network_data(frames.subset(np.arange(20)))["state"]  # 3 batches of 8
    network = state_network_for(data)
    config = TrainConfig(epochs=4, batch_size=8, max_steps=5)
    history = fit(network, data, None, config, "state", progress=False)
    assert len(history["batch_loss"]) == 5
    assert len(history["train_loss"]) == 2  # a whole epoch and two batches of the next
    assert history["epoch_end_step"] == [3, 5]
    assert history["train_loss"][1] == pytest.approx(np.mean(history["batch_loss"][3:5]))
    assert TrainConfig(epochs=1, batch_size=8, min_steps=5, max_steps=5).steps_for(400) == 5
    with pytest.raises(SafeRaceError, match="above max_steps"):
        TrainConfig(min_steps=6, max_steps=5)


def counting_losses(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Count the gradient steps trained from here on (one loss per step)."""
    steps: list[int] = []
    loss = training.training_loss

    def counted(*args, **kwargs):
        steps.append(1)
        return loss(*args, **kwargs)

    monkeypatch.setattr(training, "training_loss", counted)
    return steps


def test_a_training_resumed_before_its_cut_epoch_ends_with_the_same_weights(
    frames, monkeypatch: pytest.MonkeyPatch
):
    data = network_data(frames.subset(np.arange(20)))["state"]
    config = TrainConfig(epochs=4, batch_size=8, max_steps=5)
    runs, states, steps = [], [], counting_losses(monkeypatch)

    def keep(state: dict) -> None:  # as a resume file would, not the live tensors
        states.append(copy.deepcopy(state))

    for resume in (None, "after the first epoch"):
        torch.manual_seed(0)
        network = state_network_for(data)
        steps.clear()
        fit(network, data, None, config, "state", False, states[0] if resume else None, keep)
        runs.append(network)
    assert len(steps) == 5 - 3  # the resumed run trained only what the first epoch had not
    for name, weights in runs[0].state_dict().items():
        assert torch.equal(weights, runs[1].state_dict()[name]), name


def test_early_stopping_keeps_the_best_epochs_weights_and_stops_after_patience(frames, monkeypatch):
    data = network_data(frames.subset(np.arange(20)))["state"]
    held_out = network_data(frames.subset(np.arange(20, 28)))["state"]
    losses = iter([3.0, 1.0, 2.0, 2.5, 0.5, 0.1])  # best at epoch 2, then two worse ones
    monkeypatch.setattr(training, "validation_loss", lambda *args: next(losses))
    states = []
    network = state_network_for(data)
    config = TrainConfig(epochs=6, batch_size=8, patience=2)
    history = fit(network, data, held_out, config, "state", False, None,
                  lambda state: states.append(copy.deepcopy(state)))  # fmt: skip
    assert history["val_loss"] == [3.0, 1.0, 2.0, 2.5]  # stopped 2 epochs after the best
    assert history["best_epoch"] == [2] and states[-1]["epochs_done"] == 6  # nothing to resume
    for name, weights in network.state_dict().items():
        assert torch.equal(weights, states[1]["weights"][name]), name
    assert not torch.equal(states[1]["weights"]["output_layer.weight"],
                           states[3]["weights"]["output_layer.weight"])  # fmt: skip
    with pytest.raises(SafeRaceError, match="patience"):
        TrainConfig(patience=2, val_stretch=None)


def test_augmentation_redraws_each_image_from_its_generator(frames):
    images = torch.from_numpy(frames["image"][:16])
    first = photometric(images, torch.Generator().manual_seed(0))
    again = photometric(images, torch.Generator().manual_seed(0))
    other = photometric(images, torch.Generator().manual_seed(1))
    assert first.dtype == torch.uint8 and first.shape == images.shape
    assert torch.equal(first, again) and not torch.equal(first, other)
    brightness = first.float().mean(dim=(1, 2, 3)) - images.float().mean(dim=(1, 2, 3))
    assert brightness.std() > 5.0  # each image its own draw, not one shift for the batch
    assert torch.equal(images, torch.from_numpy(frames["image"][:16]))  # the frames untouched


def test_a_network_left_out_is_taken_unchanged_from_init(frames, tmp_path: Path):
    few = frames.subset(np.arange(24))
    control, state, metadata = train_networks(few, FEW, progress=False)
    init = save_checkpoint(tmp_path / "init.pt", control, state, metadata)
    only_control = replace(FEW, init=str(init), networks=("control",))
    new_control, kept_state, new_metadata = train_networks(few, only_control, progress=False)
    for name, weights in state.state_dict().items():
        assert torch.equal(weights, kept_state.state_dict()[name]), name
    assert not torch.equal(control.output_layer.weight, new_control.output_layer.weight)
    assert list(new_metadata["history"]) == ["control"]
    assert new_metadata["kept"] == {"state": str(init)}
    with pytest.raises(SafeRaceError, match="init is needed"):
        replace(FEW, networks=("control",))
    with pytest.raises(SafeRaceError, match="networks must be"):
        replace(FEW, init=str(init), networks=("steering",))


def test_same_seed_same_weights(frames):
    few = frames.subset(np.arange(24))
    first = train_networks(few, FEW, progress=False)
    again = train_networks(few, FEW, progress=False)
    other = train_networks(few, replace(FEW, seed=1), progress=False)
    for index in (0, 1):  # the control and the state network
        for name, weights in first[index].state_dict().items():
            assert torch.equal(weights, again[index].state_dict()[name]), name
        assert not torch.equal(first[index].output_layer.weight, other[index].output_layer.weight)


def test_checkpoint_gives_identical_outputs(frames, tmp_path: Path):
    control, state, metadata = train_networks(frames.subset(np.arange(24)), FEW, progress=False)
    path = save_checkpoint(tmp_path / "model.pt", control, state, metadata)
    loaded = load_checkpoint(path)
    images, velocity = frames["image"][:4], frames["velocity"][:4]
    for before, after, extra in ((control, loaded.control, velocity), (state, loaded.state, None)):
        expected = before.predict(images, extra, 10, torch.Generator().manual_seed(1))
        actual = after.predict(images, extra, 10, torch.Generator().manual_seed(1))
        assert np.array_equal(expected.samples, actual.samples)
    assert loaded.metadata["training"] == FEW.as_dict()
    assert loaded.metadata["image_shape"] == [64, 64, 3]
    assert len(loaded.sha256) == 64
    assert not list(tmp_path.glob(".*partial"))  # the temporary file was renamed into place


def test_checkpoint_errors(tmp_path: Path):
    with pytest.raises(SafeRaceError, match="no checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(2)}, other)
    with pytest.raises(SafeRaceError, match="not a SafeRace checkpoint"):
        load_checkpoint(other)
    (tmp_path / "text.pt").write_text("hello")
    with pytest.raises(SafeRaceError, match="not a SafeRace checkpoint"):
        load_checkpoint(tmp_path / "text.pt")


def test_validation_holds_out_a_contiguous_stretch(frames):
    mask = held_out_mask(frames, (0.1, 0.2))
    fraction = frames.lap_fraction
    assert mask.any() and (~mask).any()
    assert np.all((fraction[mask] >= 0.1) & (fraction[mask] < 0.2))
    assert not np.any((fraction[~mask] >= 0.1) & (fraction[~mask] < 0.2))
    with pytest.raises(SafeRaceError, match="validation stretch"):
        train_networks(frames, replace(FEW, val_stretch=(0.9, 1.0)), progress=False)
    with pytest.raises(SafeRaceError, match="val_stretch"):
        TrainConfig(val_stretch=(0.5, 0.4))
    everything = replace(FEW, val_stretch=None)
    _, _, metadata = train_networks(frames.subset(np.arange(16)), everything, progress=False)
    assert metadata["frames"] == {"train": 16, "validation": 0}
    assert metadata["history"]["state"]["val_loss"] == []


def test_warm_start_begins_at_the_checkpoint(frames, tiny_checkpoint):
    checkpoint = load_checkpoint(tiny_checkpoint()[0])
    tiny_steps = replace(FEW, init=str(tiny_checkpoint()[0]), learning_rate=1e-12)
    control, state, _ = train_networks(frames.subset(np.arange(24)), tiny_steps, progress=False)
    normalisation_buffers = ("image_mean", "image_std", "output_mean", "output_std")
    for warm, start in ((control, checkpoint.control), (state, checkpoint.state)):
        for name, weights in start.named_parameters():  # (BatchNorm's statistics move on)
            assert torch.allclose(warm.get_parameter(name), weights, atol=1e-6), name
        for name in normalisation_buffers:  # the checkpoint's normalisation is kept
            assert torch.equal(getattr(warm, name), getattr(start, name)), name


def test_train_and_validate_commands(tiny_checkpoint, tmp_path: Path):
    data = tiny_checkpoint()[1]
    checkpoint = tmp_path / "run.pt"
    args = ("train", str(data), "--out", str(checkpoint), "--epochs", "1", "--samples", "3")
    trained = run_cli(*args, "--val-stretch", "0.05", "0.08")
    assert trained.returncode == 0, trained.stderr
    for suffix in ("_loss.png", "_state_along_lap.png", "_validation.md", "_validation.csv"):
        assert (tmp_path / f"run{suffix}").stat().st_size > 100, suffix
    table = (tmp_path / "run_validation.md").read_text()
    assert "held-out stretch: far half" in table and "e_y_m" in table
    stereo_refused = run_cli(*args, "--stereo")
    assert stereo_refused.returncode == 2 and "stereo" in stereo_refused.stderr
    validated = run_cli("validate", str(checkpoint), str(data), "--out", str(tmp_path / "v"))
    assert validated.returncode == 0, validated.stderr
    assert (tmp_path / "v" / "validation.md").read_text().count("lab CenterLine") == 5
    assert (tmp_path / "v" / "state_along_lap_0_lab.png").stat().st_size > 10_000


def test_an_interrupted_run_resumes_to_the_same_weights(
    frames, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    few = frames.subset(np.arange(24))
    config = replace(FEW, epochs=2)
    steps = counting_losses(monkeypatch)
    expected = train_networks(few, config, progress=False)
    from_scratch = len(steps)  # 2 networks x 2 epochs
    calls = []

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == 4:  # the state network's second epoch: its first one is kept
            raise KeyboardInterrupt
        return 0.0

    resume_file = tmp_path / "run.resume.pt"
    with monkeypatch.context() as patch:
        patch.setattr("saferace.learning.training.validation_loss", interrupted)
        with pytest.raises(KeyboardInterrupt):
            train_networks(few, config, progress=False, resume_file=resume_file)
    assert resume_file.exists()
    steps.clear()
    resumed = train_networks(few, config, progress=False, resume_file=resume_file)
    assert len(steps) == from_scratch // 4  # only the state network's second epoch again
    for before, after in zip(expected[:2], resumed[:2], strict=True):
        for name, weights in before.state_dict().items():
            assert torch.equal(weights, after.state_dict()[name]), name
    with pytest.raises(SafeRaceError, match="other settings"):
        train_networks(few, replace(config, seed=3), progress=False, resume_file=resume_file)


def test_a_lone_last_frame_of_small_images_is_left_out_of_the_epochs_batches():
    """At 32x32 the backbone's last features are 1x1: BatchNorm cannot train on a batch of
    one frame, which 33 frames in batches of 32 leave at the end of every epoch."""
    rng = np.random.default_rng(0)
    images = rng.integers(0, 255, (33, 32, 32, 3), dtype=np.uint8)
    data = NetworkData(images, None, rng.normal(size=(33, 3)).astype(np.float32))
    torch.manual_seed(0)
    network = DrivingNetwork(state_config())
    history = fit(network, data, None, TrainConfig(epochs=2), "state", progress=False)
    assert len(history["batch_loss"]) == 2  # one full batch per epoch, the lone frame left out
    assert history["epoch_end_step"] == [1, 2]
    assert history["train_loss"] == pytest.approx(history["batch_loss"])


def test_the_cosine_schedule_falls_to_zero_and_resumes_where_it_was(
    frames, monkeypatch: pytest.MonkeyPatch
):
    data = network_data(frames.subset(np.arange(20)))["state"]
    config = TrainConfig(epochs=3, batch_size=8, lr_schedule="cosine", learning_rate=0.01)
    rates: list[float] = []
    step = torch.optim.Adam.step

    def recorded(self, *args, **kwargs):
        rates.append(self.param_groups[0]["lr"])
        return step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", recorded)
    states: list[dict] = []
    torch.manual_seed(0)
    keep = lambda state: states.append(copy.deepcopy(state))  # noqa: E731  (as a file would)
    fit(state_network_for(data), data, None, config, "state", False, None, keep)
    steps = config.steps_for(len(data))
    expected = [0.005 * (1 + math.cos(math.pi * k / steps)) for k in range(steps)]
    assert rates == pytest.approx(expected)
    rates.clear()
    torch.manual_seed(0)
    fit(state_network_for(data), data, None, config, "state", False, states[0], None)
    assert rates == pytest.approx(expected[len(expected) // 3 :])  # after the first epoch
    with pytest.raises(SafeRaceError, match="lr_schedule must be one of"):
        TrainConfig(lr_schedule="step")


def test_mirrored_frames_train_on_the_mirror_image_and_the_negated_state(
    frames, monkeypatch: pytest.MonkeyPatch
):
    """With ``mirror``, about half of each batch is flipped left for right, and each flipped
    frame's target is its state negated (a car left of the lane heading left, mirrored, is
    right of it heading right); the other frames keep theirs."""
    data = network_data(frames.subset(np.arange(32)), mirror=True)["state"]
    assert data.mirrored_targets == pytest.approx(-data.targets)
    assert network_data(frames.subset(np.arange(4)))["state"].mirrored_targets is None
    seen: list[tuple[np.ndarray, torch.Tensor | None, torch.Tensor]] = []
    outputs_of, loss_of = training.network_outputs, training.training_loss

    def outputs(network, data_, index, augmenter=None, flipped=None):
        seen.append((index.copy(), flipped, torch.empty(0)))
        return outputs_of(network, data_, index, augmenter, flipped)

    def loss(network, outputs_, targets):
        seen[-1] = (*seen[-1][:2], targets.detach().clone())
        return loss_of(network, outputs_, targets)

    monkeypatch.setattr(training, "network_outputs", outputs)
    monkeypatch.setattr(training, "training_loss", loss)
    network = state_network_for(data)
    config = TrainConfig(epochs=1, batch_size=32, augment=True)
    fit(network, data, None, config, "state", progress=False)
    ((index, flipped, targets),) = seen
    assert flipped is not None and 8 <= int(flipped.sum()) <= 24
    as_tensor = lambda values: torch.as_tensor(values, dtype=torch.float32)  # noqa: E731
    plain = network.normalise_outputs(as_tensor(data.targets[index]))
    mirrored = network.normalise_outputs(as_tensor(-data.targets[index]))
    assert torch.allclose(targets[flipped], mirrored[flipped])
    assert torch.allclose(targets[~flipped], plain[~flipped])
    # and the flipped frames' images are the mirror images
    network.eval()
    every = torch.ones(4, dtype=torch.bool)
    with torch.no_grad():
        flipped_out = outputs_of(network, data, np.arange(4), None, every)
        by_hand = network(torch.from_numpy(data.images[:4].copy()).flip(2))
    assert torch.allclose(flipped_out, by_hand)
    with pytest.raises(SafeRaceError, match="mono"):
        network_data(frames.subset(np.arange(2)).__class__(
            {**frames.subset(np.arange(2)).arrays,
             "image": np.zeros((2, 8, 8, 6), np.uint8)}, []), mirror=True)  # fmt: skip
