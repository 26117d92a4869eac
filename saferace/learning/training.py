"""Train both networks on collection rounds: Adam on the MSE of normalised targets.

The control network learns the expert's ``[steer_rad, target_speed_mps]`` from image and
velocities, the state network the true ``[e_y_m, e_psi_rad, kappa_radpm]`` from the image.
A contiguous stretch of the track (``val_stretch``, fractions of the lap) is held out for
validation rather than random frames, which would sit next to near-identical training
frames; ``val_stretch=None`` trains on every frame (a final model that must know the whole
lap, scored with ``saferace validate`` on other rounds). Training is seeded and
deterministic on the CPU; it can warm-start from a checkpoint (fine-tuning between DAgger
iterations, as the authors did) or load a torchvision ResNet-18 state dict into both
backbones.

With a ``resume_file`` the state of the run (weights, optimiser, random generators, losses)
is written there atomically after every epoch; a run started again with the same
configuration and data continues from the last finished epoch and ends with the weights
an uninterrupted run would have.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional

from saferace.errors import ConfigError, SafeRaceError
from saferace.eval.runner import git_revision, package_versions
from saferace.learning.checkpoint import LearnedCheckpoint, load_checkpoint, save_atomically
from saferace.learning.configs import NETWORKS, TrainConfig
from saferace.learning.device import autocast, resolve_device
from saferace.learning.ensemble import StateEnsemble
from saferace.learning.networks import (
    LOG_VARIANCE_RANGE,
    DrivingNetwork,
    NetworkConfig,
    control_config,
    load_torchvision_weights,
    state_config,
)
from saferace.learning.rounds import FrameSet
from saferace.learning.training_data import (
    NetworkData,
    held_out_mask,
    mirror_draw,
    network_data,
    network_outputs,
)
from saferace.names import STATE_UNCERTAINTY_METHODS
from saferace.progress import Progress
from saferace.version import __version__

LOG = logging.getLogger(__name__)
#: Frames sampled to estimate the images' per-channel mean and spread.
IMAGE_STATISTICS_FRAMES = 2000
#: Apart in seed between the weights of two ensemble members.
ENSEMBLE_SEED_STRIDE = 7919
#: Apart in seed between a network's batch order and its photometric draws.
AUGMENTATION_SEED_OFFSET = 104729
#: Share of a MIMO network's training inputs on which every subnetwork sees the same frame
#: (Havasi et al.'s input repetition: without it, 5 subnetworks trained on augmented frames
#: learned nothing, their held-out loss that of predicting the mean).
MIMO_INPUT_REPETITION = 0.5
#: Floor of an output's or input's standard deviation (a constant curvature on an oval).
MIN_STD = 1e-3


def normalisation(data: NetworkData, seed: int) -> dict[str, np.ndarray]:
    """Per-channel image statistics and per-component velocity and target statistics."""
    rng = np.random.default_rng(seed)
    count = min(len(data), IMAGE_STATISTICS_FRAMES)
    sample = data.images[np.sort(rng.choice(len(data), count, replace=False))]
    pixels = sample.reshape(-1, sample.shape[-1]).astype(np.float32) / 255.0
    statistics = {
        "image_mean": pixels.mean(axis=0),
        "image_std": np.maximum(pixels.std(axis=0), MIN_STD),
        "output_mean": data.targets.mean(axis=0),
        "output_std": np.maximum(data.targets.std(axis=0), MIN_STD),
    }
    if data.velocity is not None:
        statistics["velocity_mean"] = data.velocity.mean(axis=0)
        statistics["velocity_std"] = np.maximum(data.velocity.std(axis=0), MIN_STD)
    return statistics


def fit(
    network: DrivingNetwork,
    train: NetworkData,
    validation: NetworkData | None,
    config: TrainConfig,
    label: str,
    progress: bool = True,
    resume: dict | None = None,
    on_epoch: Callable[[dict], None] | None = None,
    shuffle_seed: int | None = None,
) -> dict[str, list[float]]:
    """Adam on the MSE of normalised targets (the Gaussian negative log-likelihood for a
    heteroscedastic head); returns per-batch and per-epoch losses, the step each epoch
    ended at (the last one may be cut short, see ``TrainConfig.max_steps``) and, with a
    ``patience``, the epoch whose weights were kept (``best_epoch``, counted from 1).

    Batches (and with ``config.augment`` their photometric draws) are drawn with
    ``shuffle_seed`` (default: the config's seed; an ensemble's members each draw their own).
    With ``config.patience`` the training stops once the held-out loss has not improved for
    that many epochs and the network ends with its best epoch's weights. After each epoch
    ``on_epoch`` gets the state to continue from (weights, optimiser, generators, losses,
    epochs done, the best weights); ``resume`` is such a state.
    """
    device = resolve_device()
    network.to(device)
    network.to(memory_format=torch.channels_last)
    optimizer = torch.optim.Adam(network.parameters(), lr=config.learning_rate)
    seed = config.seed if shuffle_seed is None else shuffle_seed
    generator = torch.Generator().manual_seed(seed)
    augmenter = torch.Generator().manual_seed(seed + AUGMENTATION_SEED_OFFSET)
    history: dict[str, list[float]] = {
        "batch_loss": [],
        "train_loss": [],
        "val_loss": [],
        "epoch_end_step": [],
        "best_epoch": [],
    }
    first_epoch, best = 0, None
    if resume is not None:
        network.load_state_dict(resume["weights"])
        optimizer.load_state_dict(resume["optimizer"])
        generator.set_state(resume["generator"])
        augmenter.set_state(resume["augmenter"])
        torch.set_rng_state(resume["torch_rng"])  # dropout's masks
        history, first_epoch, best = resume["history"], resume["epochs_done"], resume["best"]

    def normalised(raw: np.ndarray) -> torch.Tensor:
        return network.normalise_outputs(torch.as_tensor(raw, dtype=torch.float32, device=device))

    targets = normalised(train.targets)
    mirrored = None if train.mirrored_targets is None else normalised(train.mirrored_targets)
    batches = math.ceil(len(train) / config.batch_size)
    steps = config.steps_for(len(train))
    epochs = math.ceil(steps / batches)
    with Progress(
        steps,
        f"train {label}",
        "batch",
        enabled=progress,
        initial=min(first_epoch * batches, steps),
    ) as bar:
        for epoch in range(first_epoch, epochs):
            network.train()
            order = epoch_order(len(train), network.config.subnetworks, generator)
            order = order[..., : (steps - epoch * batches) * config.batch_size]  # the last cut
            total, trained = 0.0, 0
            for start in range(0, order.shape[-1], config.batch_size):
                index = order[..., start : start + config.batch_size]
                bar.update()
                if index.shape[-1] == 1:  # BatchNorm cannot train on one frame of 1x1 features
                    continue  # (32x32 images); shuffled, the frame is in the next epoch's batches
                flipped = mirror_draw(train, index, augmenter if config.augment else None)
                batch_targets = targets[index.T]
                if flipped is not None and mirrored is not None:
                    batch_targets = torch.where(
                        (flipped.T if flipped.ndim == 2 else flipped)[..., None].to(device),
                        mirrored[index.T],
                        batch_targets,
                    )
                with autocast(device):
                    outputs = network_outputs(
                        network, train, index, augmenter if config.augment else None, flipped
                    )
                    loss = training_loss(network, outputs.float(), batch_targets)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                if config.lr_schedule == "cosine":  # from the step count: resumes exactly
                    done = len(history["batch_loss"]) / steps
                    for group in optimizer.param_groups:
                        group["lr"] = 0.5 * config.learning_rate * (1.0 + math.cos(math.pi * done))
                optimizer.step()
                value = loss.item()
                history["batch_loss"].append(value)
                total += value * index.shape[-1]
                trained += index.shape[-1]
                bar.show(f"epoch={epoch + 1}, loss={value:.4f}")
            history["train_loss"].append(total / max(trained, 1))
            history["epoch_end_step"].append(len(history["batch_loss"]))
            losses = f"train loss {history['train_loss'][-1]:.4f}"
            if validation is not None and len(validation):
                history["val_loss"].append(validation_loss(network, validation, config.batch_size))
                bar.show(f"epoch={epoch + 1}, val={history['val_loss'][-1]:.4f}")
                losses += f", validation loss {history['val_loss'][-1]:.4f}"
                if config.patience and (best is None or history["val_loss"][-1] < best["loss"]):
                    best = {"epoch": epoch + 1, "loss": history["val_loss"][-1],
                            "weights": copy.deepcopy(network.state_dict())}  # fmt: skip
            bar.report(f"epoch {epoch + 1}/{epochs}", losses)
            stop = best is not None and epoch + 1 - best["epoch"] >= config.patience
            if on_epoch is not None:
                on_epoch(
                    {
                        "epochs_done": epochs if stop else epoch + 1,
                        "weights": network.state_dict(),
                        "optimizer": optimizer.state_dict(),
                        "generator": generator.get_state(),
                        "augmenter": augmenter.get_state(),
                        "torch_rng": torch.get_rng_state(),
                        "history": history,
                        "best": best,
                    }
                )
            if stop:
                break
    if best is not None:
        network.load_state_dict(best["weights"])
        history["best_epoch"] = [best["epoch"]]
    network.eval()
    return history


def epoch_order(count: int, subnetworks: int, generator: torch.Generator) -> np.ndarray:
    """One epoch's order of ``count`` frames: ``(count,)``, or for a MIMO network one
    independent order per subnetwork ``(K, count)``, so each trains on its own batches,
    except that a share :data:`MIMO_INPUT_REPETITION` of the places give every subnetwork
    the first one's frame."""
    first = torch.randperm(count, generator=generator)
    if subnetworks == 1:
        return first.numpy()
    others = torch.stack(
        [torch.randperm(count, generator=generator) for _ in range(1, subnetworks)]
    )
    repeated = torch.rand(count, generator=generator) < MIMO_INPUT_REPETITION
    return torch.cat([first[None], torch.where(repeated, first, others)]).numpy()


def training_loss(
    network: DrivingNetwork, outputs: torch.Tensor, targets: torch.Tensor
) -> torch.Tensor:
    """The MSE of normalised targets, or for heteroscedastic heads the Gaussian negative
    log-likelihood of their means and variances (``targets`` ``(B, K, outputs)`` for K MIMO
    subnetworks, each its own frame's; ``(B, outputs)`` for every packed member)."""
    if not network.config.log_variance:
        return functional.mse_loss(outputs, targets)
    count = targets.shape[-1]
    per_member = outputs.reshape(len(outputs), network.config.members, 2 * count)
    log_variance = per_member[..., count:].clamp(*LOG_VARIANCE_RANGE)
    means = per_member[..., :count]
    targets = targets.reshape(len(outputs), -1, count).expand(means.shape)
    return functional.gaussian_nll_loss(means, targets, log_variance.exp())


@torch.inference_mode()
def validation_loss(network: DrivingNetwork, data: NetworkData, batch_size: int) -> float:
    """MSE of normalised targets with dropout off (of the means, and of a MIMO network's
    subnetworks' mean, for heteroscedastic heads: comparable with a dropout network's)."""
    network.eval()
    targets = network.normalise_outputs(
        torch.as_tensor(data.targets, dtype=torch.float32, device=network.device)
    )
    count = targets.shape[1]
    width = 2 * count if network.config.log_variance else count
    total = 0.0
    for start in range(0, len(data), batch_size):
        index = np.arange(start, min(start + batch_size, len(data)))
        with autocast(network.device):
            outputs = network_outputs(network, data, index).float()
        outputs = outputs.reshape(len(index), -1, width)
        error = outputs[..., :count].mean(dim=1) - targets[index]
        total += float((error**2).mean(dim=1).sum())
    return total / len(data)


def train_networks(
    frames: FrameSet,
    config: TrainConfig,
    progress: bool = True,
    resume_file: str | Path | None = None,
    mirror: bool = False,
) -> tuple[DrivingNetwork | None, DrivingNetwork | StateEnsemble, dict]:
    """Train the control and the state network (or ensemble); return them and the run's
    metadata. Trained alone, without an ``init``, the state network makes a perception
    model: no control network (None).

    ``resume_file``: where to keep the run's state after every epoch, and to continue from.
    The metadata's ``history`` holds the networks trained (an ensemble's first member;
    ``member_history`` the others'), ``kept`` where the others came from (see
    ``TrainConfig.networks``). ``mirror``: the state network also trains on its frames
    mirrored left for right (with augmentation; :func:`mirrored_state`).
    """
    if config.state_uncertainty not in STATE_UNCERTAINTY_METHODS:  # auto: a DAgger run's
        raise ConfigError(
            "state_uncertainty",
            f"must name a method ({', '.join(STATE_UNCERTAINTY_METHODS)}) to train, got "
            f"{config.state_uncertainty!r} (a DaggerConfig settles auto)",
        )
    held_out = held_out_mask(frames, config.val_stretch)
    if held_out.all() or (config.val_stretch is not None and not held_out.any()):
        raise SafeRaceError(
            f"the validation stretch {config.val_stretch} of the lap holds "
            f"{int(held_out.sum())} of {len(frames)} frames: choose --val-stretch so that "
            "both training and validation frames remain"
        )
    train_frames, validation_frames = frames.subset(~held_out), frames.subset(held_out)
    stereo = frames["image"].shape[-1] == 6
    initial = load_checkpoint(config.init) if config.init else None
    history = {}
    started = time.perf_counter()
    train_data = network_data(train_frames, mirror)
    validation_data = network_data(validation_frames)
    fingerprint = {
        "training": config.as_dict(),
        **({"mirror": True} if mirror else {}),  # runs from before mirroring still resume
        "data": [(str(Path(m["path"]).resolve()), m["frame_count"]) for m in frames.manifests],
    }
    run = _resumed_run(resume_file, fingerprint)
    trained: dict[str, list[DrivingNetwork]] = {}
    member_history = {}
    for unit in training_units(config, stereo):
        name = unit.network
        torch.manual_seed(unit.seed)
        network = DrivingNetwork(unit.config)
        source = None if initial is None else _initial_unit(initial, unit, config.init)
        if name not in config.networks:
            continue
        if unit.name in run["done"]:
            network.load_state_dict(run["done"][unit.name]["weights"])
            network.eval()
            losses = run["done"][unit.name]["history"]
        else:
            if source is not None:
                network.load_state_dict(source.state_dict())  # its normalisation too
            else:
                if config.backbone_weights:
                    load_torchvision_weights(network, config.backbone_weights)
                network.set_normalisation(normalisation(train_data[name], config.seed))
            current = run["current"] if run["current"].get("name") == unit.name else None

            def keep(state: dict, unit_name: str = unit.name) -> None:
                run["current"] = {"name": unit_name, **state}
                if resume_file is not None:
                    save_atomically(run, resume_file)

            losses = fit(
                network, train_data[name], validation_data[name], config, unit.name, progress,
                current, keep, unit.shuffle_seed,
            )  # fmt: skip
            run["done"][unit.name] = {"weights": network.state_dict(), "history": losses}
        if unit.member == 0:
            history[name] = losses
        else:
            member_history[unit.name] = losses
        trained.setdefault(name, []).append(network)
    networks = {
        name: _assembled(trained[name])
        if name in config.networks
        else None
        if initial is None
        else getattr(initial, name)
        for name in NETWORKS
    }
    control, state = networks["control"], networks["state"]
    assert control is None or isinstance(control, DrivingNetwork), "never an ensemble"
    assert state is not None, "every training makes or keeps a state network"
    metadata = {
        "training": config.as_dict(),
        "image_shape": list(frames["image"].shape[1:]),
        "frames": {"train": len(train_frames), "validation": len(validation_frames)},
        "data": [_round_summary(manifest) for manifest in frames.manifests],
        "history": history,
        "member_history": member_history,
        "kept": {name: config.init for name in NETWORKS if name not in config.networks},
        "train_seconds": time.perf_counter() - started,
        "saferace_version": __version__,
        "git_revision": git_revision(),
        "packages": package_versions(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    return control, state, metadata


@dataclass(frozen=True)
class TrainingUnit:
    """One network a training run fits: the control network, the state network, or one
    member of the state ensemble (``member`` > 0 for all but the first), with the seeds of
    its weights and of its batches."""

    name: str
    network: str
    member: int
    config: NetworkConfig
    seed: int
    shuffle_seed: int


def training_units(config: TrainConfig, stereo: bool) -> list[TrainingUnit]:
    """The networks ``config`` trains, in order; the control network and a dropout state
    network keep the seeds they have always had."""
    units = [TrainingUnit("control", "control", 0, control_config(stereo, config.dropout),
                          config.seed, config.seed)]  # fmt: skip
    if config.state_uncertainty == "mc-dropout":
        state = state_config(stereo, config.dropout)
        return [*units, TrainingUnit("state", "state", 0, state, config.seed + 1, config.seed)]
    if config.state_uncertainty == "heteroscedastic":
        gaussian = state_config(stereo, 0.0, log_variance=True)
        return [*units, TrainingUnit("state", "state", 0, gaussian, config.seed + 1, config.seed)]
    if config.state_uncertainty == "mimo":
        mimo = state_config(stereo, 0.0, log_variance=True, subnetworks=config.ensemble_members)
        return [*units, TrainingUnit("state", "state", 0, mimo, config.seed + 1, config.seed)]
    if config.state_uncertainty == "packed":
        packing = (config.ensemble_members, config.packed_alpha, config.packed_gamma)
        packed = state_config(stereo, 0.0, log_variance=True, packed=packing)
        return [*units, TrainingUnit("state", "state", 0, packed, config.seed + 1, config.seed)]
    member_config = state_config(stereo, dropout=0.0, log_variance=True)
    for member in range(config.ensemble_members):
        name = "state" if member == 0 else f"state_member_{member}"
        seed = config.seed + 1 + ENSEMBLE_SEED_STRIDE * member
        units.append(TrainingUnit(name, "state", member, member_config, seed, config.seed + member))
    return units


def _initial_unit(
    initial: LearnedCheckpoint, unit: TrainingUnit, path: str | None
) -> DrivingNetwork:
    """The network of checkpoint ``initial`` that ``unit`` starts from (its config checked)."""
    source = getattr(initial, unit.network)
    if isinstance(source, StateEnsemble):
        source = source.members[unit.member] if unit.member < len(source.members) else None
    elif unit.member > 0:
        source = None
    if source is None or source.config != unit.config:
        found = "no such network" if source is None else source.config
        raise SafeRaceError(
            f"--init {path} has {found} for the {unit.name} network; the training needs "
            f"{unit.config} (train from scratch to change the state uncertainty or members)"
        )
    return source


def _assembled(networks: list[DrivingNetwork]) -> DrivingNetwork | StateEnsemble:
    """One trained network, or the ensemble of its members."""
    return networks[0] if len(networks) == 1 else StateEnsemble(networks)


def _resumed_run(resume_file: str | Path | None, fingerprint: dict) -> dict:
    """The state a previous, interrupted run left in ``resume_file``, or a fresh one."""
    fresh = {"fingerprint": fingerprint, "done": {}, "current": {}}
    if resume_file is None or not Path(resume_file).exists():
        return fresh
    try:
        run = torch.load(resume_file, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many kinds for a damaged file
        raise SafeRaceError(
            f"cannot read the interrupted training run in {resume_file} ({exc}): delete it to "
            "start over"
        ) from None
    if run["fingerprint"] != fingerprint:
        raise SafeRaceError(
            f"{resume_file} holds an interrupted training run with other settings or data "
            f"({run['fingerprint']}); run it again with those, or delete the file to start over"
        )
    LOG.warning("resuming the interrupted training run in %s", resume_file)
    return run


def _round_summary(manifest: dict) -> dict:
    config = manifest["config"]
    return {
        "path": manifest["path"],
        "frame_count": manifest["frame_count"],
        **{key: config.get(key) for key in ("agent", "task", "track", "perturbation", "safety")},
    }
