"""The paper's two networks (Sec. 2.4 and 3.4): ResNet-18 features, a dropout head, MC dropout.

Both take the onboard image, uint8 ``(N, H, W, C)`` with 3 channels (mono) or 6 (the stereo
pair stacked, as on the paper's RC car), through torchvision's ResNet-18 without its
classification layer (512 features). The control network ``M_com`` appends the measured
``[v_x, v_y, r]`` and outputs ``[steer_rad, target_speed_mps]``; the state network ``M_st``
outputs ``[e_y_m, e_psi_rad, kappa_radpm]`` from the image alone. Normalisation of every
input and output lives in the network's buffers, so a checkpoint carries it.

The head, as in the authors' code: dropout then ``Linear(512, 128)`` for the image,
``Linear(3, 64)`` for the velocities, both through a ReLU, concatenated, dropout again, and a
linear layer to the outputs. MC dropout (paper Sec. 3.4, Gal and Ghahramani 2016): the
backbone runs once per frame with BatchNorm on its running statistics, the head is sampled
``n`` times in one batch with dropout on, and the samples' mean and (population) standard
deviation are the prediction and its spread.

A prediction moves its inputs to the device in one copy and its results back in one
(:mod:`saferace.learning.transfer`); on CUDA the work between is one replayed graph
(:mod:`saferace.learning.cuda_graphs`), on the CPU a package compiled for the machine with
the weights frozen in (:mod:`saferace.learning.cpu_compile`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torchvision
from torch import nn
from torch.nn import functional

from saferace.errors import SafeRaceError
from saferace.learning.cpu_compile import CompiledStep
from saferace.learning.cuda_graphs import GraphCache
from saferace.learning.packed import GroupedLinear, PackedResNet18, check_packing
from saferace.learning.transfer import download, upload

CONTROL_OUTPUTS = ("steer_rad", "target_speed_mps")
STATE_OUTPUTS = ("e_y_m", "e_psi_rad", "kappa_radpm")
VELOCITY_INPUTS = ("v_x_mps", "v_y_mps", "yaw_rate_radps")
FEATURES = 512  # ResNet-18's feature width
#: The log-variances (of normalised outputs) a heteroscedastic head is held within.
LOG_VARIANCE_RANGE = (-12.0, 6.0)


@dataclass(frozen=True)
class NetworkConfig:
    """Shape of one network: its outputs, input channels and head; ``log_variance``: a
    heteroscedastic head that also outputs each output's log-variance (an ensemble member,
    trained on the Gaussian negative log-likelihood); ``subnetworks`` K > 1: a MIMO ensemble
    (Havasi et al., ICLR 2021) of K heteroscedastic subnetworks in one ResNet-18, each with
    its own input channels and outputs, trained on independently drawn frames; predicting,
    every subnetwork sees the same frame, so one forward pass gives the whole ensemble.
    ``packed`` M > 1: a packed ensemble (:mod:`saferace.learning.packed`) of M independent
    heteroscedastic members in grouped layers ``alpha`` times as wide, ``gamma`` groups each,
    all trained on the same frames."""

    outputs: tuple[str, ...]
    in_channels: int = 3
    uses_velocity: bool = True
    dropout: float = 0.2
    hidden: int = 128
    velocity_hidden: int = 64
    log_variance: bool = False
    subnetworks: int = 1
    packed: int = 1
    alpha: float = 2.0
    gamma: int = 1

    def __post_init__(self) -> None:
        if self.in_channels not in (3, 6):
            raise SafeRaceError(
                f"in_channels must be 3 (mono) or 6 (stereo), got {self.in_channels}"
            )
        if not 0.0 <= self.dropout < 1.0:
            raise SafeRaceError(f"dropout must be in [0, 1), got {self.dropout}")
        if not self.outputs:
            raise SafeRaceError("a network needs at least one output")
        if self.subnetworks < 1:
            raise SafeRaceError(f"subnetworks must be at least 1, got {self.subnetworks}")
        if self.subnetworks > 1 and not self.log_variance:
            raise SafeRaceError("MIMO subnetworks need heteroscedastic heads (log_variance)")
        if self.packed > 1:
            check_packing(self.packed, self.alpha, self.gamma)
            if not self.log_variance or self.uses_velocity or self.subnetworks > 1:
                raise SafeRaceError(
                    "a packed ensemble is a state network of heteroscedastic members "
                    "(log_variance, no velocities, no MIMO subnetworks)"
                )

    @property
    def members(self) -> int:
        """Gaussians the heteroscedastic head outputs: MIMO subnetworks or packed members."""
        return max(self.subnetworks, self.packed)

    def as_dict(self) -> dict:
        """The fields, without the packing of a network that is not packed (so that a
        checkpoint without one reads in versions from before packed ensembles)."""
        values = asdict(self)
        if self.packed == 1:
            for name in ("packed", "alpha", "gamma"):
                del values[name]
        return values

    @classmethod
    def from_dict(cls, values: dict) -> NetworkConfig:
        return cls(**{**values, "outputs": tuple(values["outputs"])})


def control_config(stereo: bool = False, dropout: float = 0.2) -> NetworkConfig:
    """``M_com``: image and velocities to ``[steer_rad, target_speed_mps]``."""
    return NetworkConfig(CONTROL_OUTPUTS, 6 if stereo else 3, uses_velocity=True, dropout=dropout)


def state_config(
    stereo: bool = False,
    dropout: float = 0.2,
    log_variance: bool = False,
    subnetworks: int = 1,
    packed: tuple[int, float, int] | None = None,
) -> NetworkConfig:
    """``M_st``: image to ``[e_y_m, e_psi_rad, kappa_radpm]`` (and their log-variances, per
    MIMO subnetwork or ``packed`` member: ``(members, alpha, gamma)``)."""
    members, alpha, gamma = packed or (1, NetworkConfig.alpha, NetworkConfig.gamma)
    return NetworkConfig(
        STATE_OUTPUTS,
        6 if stereo else 3,
        uses_velocity=False,
        dropout=dropout,
        log_variance=log_variance,
        subnetworks=subnetworks,
        packed=members,
        alpha=alpha,
        gamma=gamma,
    )


@dataclass(frozen=True)
class Prediction:
    """MC-dropout prediction in physical units: ``mean`` and ``std`` ``(N, outputs)``,
    ``samples`` ``(N, n, outputs)``; ``features`` ``(N, F)``: the backbone's (what an
    out-of-distribution monitor looks at)."""

    mean: np.ndarray
    std: np.ndarray
    samples: np.ndarray
    features: np.ndarray


def mixture(means: np.ndarray, stds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std of an equal-weight Gaussian mixture from the members' ``(K, N,
    outputs)`` means and stds: ``mean(mu_k)`` and ``sqrt(mean(sigma_k^2) + var(mu_k))``."""
    means, stds = np.asarray(means, float), np.asarray(stds, float)
    variance = np.mean(stds**2, axis=0) + np.var(means, axis=0)
    return means.mean(axis=0), np.sqrt(variance)


def gaussian_samples(means: torch.Tensor, stds: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """From members' ``(N, K, outputs)`` means and stds, on their device: the mixture's
    mean and std (as :func:`mixture`) and every member's two points ``mean_k +- std_k``
    ``(N, 2 K, outputs)``, whose mean and population spread are exactly the mixture's."""
    variance = stds.square().mean(dim=1) + means.var(dim=1, correction=0)
    samples = torch.cat([means - stds, means + stds], dim=1)
    return means.mean(dim=1), variance.sqrt(), samples


def frames(image: np.ndarray | torch.Tensor) -> torch.Tensor:
    """``(H, W, C)`` or ``(N, H, W, C)`` images as an ``(N, H, W, C)`` tensor (no copy)."""
    image = torch.as_tensor(image)
    return image[None] if image.ndim == 3 else image


def resnet18_features(in_channels: int) -> nn.Module:
    """torchvision's ResNet-18 (random weights), ``in_channels`` in, 512 features out."""
    backbone = torchvision.models.resnet18(weights=None)
    if in_channels != 3:
        backbone.conv1 = nn.Conv2d(in_channels, 64, kernel_size=7, stride=2, padding=3, bias=False)
    backbone.fc = nn.Identity()
    return backbone


class DrivingNetwork(nn.Module):
    """ResNet-18 features (+ velocities) -> dropout head -> ``config.outputs``.

    ``forward`` gives normalised outputs (for training); :meth:`predict` gives physical
    units with the MC-dropout spread.
    """

    # Buffers (registered in __init__): the inputs' and outputs' normalisation.
    image_mean: torch.Tensor
    image_std: torch.Tensor
    velocity_mean: torch.Tensor
    velocity_std: torch.Tensor
    output_mean: torch.Tensor
    output_std: torch.Tensor

    def __init__(self, config: NetworkConfig) -> None:
        super().__init__()
        self.config = config
        channels, outputs = config.in_channels, len(config.outputs)
        per_member = 2 * outputs if config.log_variance else outputs
        self.image_branch: nn.Module
        self.output_layer: nn.Module
        self.backbone: nn.Module
        if config.packed > 1:
            packed = PackedResNet18(channels, config.packed, config.alpha, config.gamma)
            self.backbone, features = packed, packed.features_per_member
            self.image_branch = GroupedLinear(config.packed, features, config.hidden)
            self.output_layer = GroupedLinear(config.packed, config.hidden, per_member)
        else:
            self.backbone = resnet18_features(channels * config.subnetworks)
            self.image_branch = nn.Linear(FEATURES, config.hidden)
            width = config.hidden
            if config.uses_velocity:
                self.velocity_branch = nn.Linear(len(VELOCITY_INPUTS), config.velocity_hidden)
                width += config.velocity_hidden
            self.output_layer = nn.Linear(width, per_member * config.subnetworks)
        self.register_buffer("image_mean", torch.full((channels,), 0.5))
        self.register_buffer("image_std", torch.full((channels,), 0.25))
        self.register_buffer("velocity_mean", torch.zeros(len(VELOCITY_INPUTS)))
        self.register_buffer("velocity_std", torch.ones(len(VELOCITY_INPUTS)))
        self.register_buffer("output_mean", torch.zeros(outputs))
        self.register_buffer("output_std", torch.ones(outputs))
        self._compiled = CompiledStep(self)
        self._graphs = GraphCache(self._compiled)

    def _apply(self, fn, recurse=True):  # type: ignore[no-untyped-def]  # nn.Module's
        """Moving the weights (``to``, ``cuda``, ``half``) leaves captured graphs and
        compiled packages stale."""
        self._graphs.clear()
        self._compiled.clear()
        return super()._apply(fn, recurse)

    @property
    def device(self) -> torch.device:
        """Where the weights are: inputs are moved here, predictions come back to the CPU."""
        return self.image_mean.device

    def set_normalisation(self, statistics: dict[str, np.ndarray]) -> None:
        """Set the ``*_mean``/``*_std`` buffers from arrays of the training data."""
        for name, values in statistics.items():
            buffer = getattr(self, name)
            buffer.copy_(torch.as_tensor(np.asarray(values), dtype=buffer.dtype))

    def features(self, image: torch.Tensor) -> torch.Tensor:
        """``(N, 512)`` backbone features of uint8 images ``(N, H, W, C)``; a MIMO network
        takes each subnetwork's image side by side ``(N, H, W, K C)``, or one image that
        every subnetwork sees."""
        channels, subnetworks = self.config.in_channels, self.config.subnetworks
        if image.ndim == 4 and subnetworks > 1 and image.shape[-1] == channels:
            image = image.repeat(1, 1, 1, subnetworks)
        if image.ndim != 4 or image.shape[-1] != channels * subnetworks:
            raise SafeRaceError(
                f"expected images (N, H, W, {channels * subnetworks}), got {tuple(image.shape)}"
            )
        # NHWC -> NCHW as a view: channels-last memory, the fast layout for CPU convolutions.
        x = image.to(self.device).permute(0, 3, 1, 2).float() / 255.0
        mean, std = self.image_mean.repeat(subnetworks), self.image_std.repeat(subnetworks)
        return self.backbone((x - mean[:, None, None]) / std[:, None, None])

    def head(
        self,
        features: torch.Tensor,
        velocity: torch.Tensor | None,
        sample: bool,
        masks: tuple[torch.Tensor, ...] = (),
    ) -> torch.Tensor:
        """Normalised outputs from features; ``sample``: dropout on (training or MC), with
        the two dropouts' keep ``masks`` where given (see :meth:`dropout_masks`)."""
        first, second = masks or (None, None)
        x = functional.relu(self.image_branch(self._dropout(features, sample, first)))
        if self.config.uses_velocity:
            if velocity is None:
                raise SafeRaceError("the control network needs the velocities [v_x, v_y, r]")
            v = (velocity.to(self.device).float() - self.velocity_mean) / self.velocity_std
            x = torch.cat([x, functional.relu(self.velocity_branch(v))], dim=1)
        return self.output_layer(self._dropout(x, sample, second))

    def dropout_masks(
        self, rows: int, generator: torch.Generator | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The head's two keep masks for ``rows`` samples, drawn on the CPU (from
        ``generator`` where given): repeatable samples on any device."""
        config = self.config
        width = config.hidden + (config.velocity_hidden if config.uses_velocity else 0)
        first = torch.rand((rows, FEATURES), generator=generator) >= config.dropout
        return first, torch.rand((rows, width), generator=generator) >= config.dropout

    def forward(self, image: torch.Tensor, velocity: torch.Tensor | None = None) -> torch.Tensor:
        return self.head(self.features(image), velocity, sample=self.training)

    def normalise_outputs(self, values: torch.Tensor) -> torch.Tensor:
        return (values - self.output_mean) / self.output_std

    def denormalise_outputs(self, values: torch.Tensor) -> torch.Tensor:
        return values * self.output_std + self.output_mean

    @torch.inference_mode()
    def predict(
        self,
        image: np.ndarray | torch.Tensor,
        velocity: np.ndarray | torch.Tensor | None = None,
        n_samples: int = 10,
        generator: torch.Generator | Sequence[torch.Generator] | None = None,
    ) -> Prediction:
        """Mean and spread of ``n_samples`` MC-dropout passes of the head.

        ``image`` is ``(H, W, C)`` or ``(N, H, W, C)`` uint8. With ``n_samples=1`` or no
        dropout the head runs once without dropout and the spread is exactly 0; a
        heteroscedastic head runs once and gives its own variance. ``generator``: where the
        dropout masks come from, or one generator per frame (N episodes driven together,
        each with the masks it would draw alone). Call ``eval()`` first: BatchNorm must use
        its running statistics.
        """
        if self.training:
            raise SafeRaceError("call eval() before predict(): MC dropout samples the head only")
        if n_samples < 1:
            raise SafeRaceError(f"n_samples must be at least 1, got {n_samples}")
        image = frames(image)
        inputs = [image]
        if self.config.uses_velocity:
            if velocity is None:
                raise SafeRaceError("the control network needs the velocities [v_x, v_y, r]")
            inputs.append(torch.as_tensor(velocity, dtype=torch.float32).reshape(len(image), -1))
        sampled = n_samples > 1 and self.config.dropout > 0.0 and not self.config.log_variance
        if sampled:
            if isinstance(generator, Sequence):
                if len(generator) != len(image):
                    raise SafeRaceError(f"{len(generator)} generators for {len(image)} frames")
                per_frame = [self.dropout_masks(n_samples, each) for each in generator]
                inputs.extend(torch.cat(masks) for masks in zip(*per_frame, strict=True))
            else:
                inputs.extend(self.dropout_masks(len(image) * n_samples, generator))
        return Prediction(*download(*self._graphs(*upload(self.device, *inputs))))

    def predict_tensors(self, image: torch.Tensor, *rest: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """:meth:`predict`'s work on the device: ``(image, [velocity], [keep masks])`` to
        the mean, std, samples and features, as tensors (what a CUDA graph replays)."""
        velocity = rest[0] if self.config.uses_velocity else None
        masks = rest[1:] if self.config.uses_velocity else rest
        features = self.features(image)
        if self.config.log_variance:
            gaussians = self.member_gaussians(self.head(features, velocity, False))
            return (*gaussian_samples(*gaussians), features)
        if not masks:
            samples = self.head(features, velocity, sample=False)[:, None, :]
        else:
            n_samples = len(masks[0]) // len(image)
            repeated = None if velocity is None else velocity.repeat_interleave(n_samples, 0)
            outputs = self.head(features.repeat_interleave(n_samples, 0), repeated, True, masks)
            samples = outputs.reshape(len(image), n_samples, -1)
        samples = self.denormalise_outputs(samples)
        mean = samples.mean(dim=1)
        std = torch.zeros_like(mean) if samples.shape[1] == 1 else samples.std(dim=1, correction=0)
        return mean, std, samples, features

    def member_gaussians(self, outputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each member's (MIMO subnetwork's, packed member's) mean and std in physical
        units, ``(N, K, outputs)``, from a heteroscedastic head's outputs."""
        count = len(self.config.outputs)
        per_member = outputs.reshape(len(outputs), self.config.members, 2 * count)
        log_variance = per_member[..., count:].clamp(*LOG_VARIANCE_RANGE)
        stds = torch.exp(0.5 * log_variance) * self.output_std
        return self.denormalise_outputs(per_member[..., :count]), stds

    def _dropout(self, x: torch.Tensor, sample: bool, keep: torch.Tensor | None) -> torch.Tensor:
        p = self.config.dropout
        if not sample or p == 0.0:
            return x
        if keep is None:
            return functional.dropout(x, p, training=True)
        return x * keep / (1.0 - p)


def load_torchvision_weights(network: DrivingNetwork, path: str | Path) -> None:
    """Load a torchvision-format ResNet-18 state dict (e.g. ImageNet weights) into the backbone.

    The classification layer (``fc.*``) is dropped. For 6 input channels the first
    convolution's 3-channel kernel is used for both images, halved, so that a stereo pair of
    two identical images gives the pretrained response.
    """
    try:
        weights = torch.load(Path(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many kinds for a file that holds no state dict
        raise SafeRaceError(f"cannot read ResNet-18 weights from {path}: {exc}") from None
    if not isinstance(weights, dict) or "conv1.weight" not in weights:
        raise SafeRaceError(
            f"{path} is not a torchvision ResNet-18 state dict (no 'conv1.weight'); save one "
            "with torch.save(torchvision.models.resnet18(weights=...).state_dict(), path)"
        )
    weights = {k: v for k, v in weights.items() if not k.startswith("fc.")}
    conv = weights["conv1.weight"]
    channels = network.config.in_channels
    if conv.shape[1] == 3 and channels == 6:
        weights["conv1.weight"] = torch.cat([conv, conv], dim=1) / 2.0
    try:
        network.backbone.load_state_dict(weights)
    except RuntimeError as exc:
        raise SafeRaceError(f"{path} does not fit ResNet-18: {exc}") from None
