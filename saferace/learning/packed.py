"""Packed-Ensembles (Laurent et al., ICLR 2023): M independent networks in one forward pass.

A packed ResNet-18 is torchvision's ResNet-18 with every layer widened by ``alpha`` and
every convolution after the first split into ``M gamma`` groups: member ``m`` owns the
``m``-th block of each layer's channels, and a grouped convolution never mixes blocks, so
the members are as independent as a deep ensemble's (changing one member's weights changes
only its outputs). The first convolution reads the shared image with one group: each of its
output channels belongs to one member and depends on the image alone. BatchNorm, the
ReLUs and the pooling act per channel. Each member's features (its block of the pooled
channels) feed its own head (:class:`GroupedLinear`).

The cost: a grouped convolution of ``C`` channels in ``G`` groups does ``C^2 / G`` of a
dense one's work, so ``M = 5, alpha = 2, gamma = 1`` is about ``alpha^2 / (M gamma) =
0.8`` of one ResNet-18 (``benchmarks/learned_step_speed.py`` times it beside the deep
ensemble).
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional

from saferace.errors import SafeRaceError

#: ResNet-18's stage widths (channels) and its stem's.
RESNET18_WIDTHS = (64, 128, 256, 512)


def packed_width(channels: int, members: int, alpha: float, gamma: int) -> int:
    """A packed layer's channels: ``alpha`` times ``channels``, rounded up to whole groups
    (``members * gamma`` of them, each member ``gamma``)."""
    groups = members * gamma
    return math.ceil(alpha * channels / groups) * groups


def check_packing(members: int, alpha: float, gamma: int) -> None:
    """Raise a :class:`SafeRaceError` naming the first packing setting out of range."""
    if members < 2:
        raise SafeRaceError(f"a packed ensemble needs at least 2 members, got {members}")
    if not alpha > 0.0:
        raise SafeRaceError(f"the width factor alpha must be positive, got {alpha}")
    if gamma < 1:
        raise SafeRaceError(f"the groups per member gamma must be at least 1, got {gamma}")


class PackedBasicBlock(nn.Module):
    """ResNet's basic block (two 3x3 convolutions and a shortcut), each convolution
    grouped."""

    def __init__(self, in_channels: int, channels: int, stride: int, groups: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, channels, 3, stride, 1, bias=False, groups=groups)
        self.bn1 = nn.BatchNorm2d(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, 1, 1, bias=False, groups=groups)
        self.bn2 = nn.BatchNorm2d(channels)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_channels != channels:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_channels, channels, 1, stride, bias=False, groups=groups),
                nn.BatchNorm2d(channels),
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = functional.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        shortcut = x if self.downsample is None else self.downsample(x)
        return functional.relu(out + shortcut)


class PackedResNet18(nn.Module):
    """``members`` ResNet-18s (widths times ``alpha``, ``gamma`` groups each) in grouped
    layers; ``forward`` gives ``(N, members * features_per_member)`` features, member by
    member."""

    def __init__(self, in_channels: int, members: int, alpha: float, gamma: int) -> None:
        super().__init__()
        check_packing(members, alpha, gamma)
        groups = members * gamma
        widths = [packed_width(width, members, alpha, gamma) for width in RESNET18_WIDTHS]
        self.members = members
        self.features_per_member = widths[-1] // members
        self.conv1 = nn.Conv2d(in_channels, widths[0], 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(widths[0])
        stages, previous = [], widths[0]
        for stage, width in enumerate(widths):
            stride = 1 if stage == 0 else 2
            blocks = [
                PackedBasicBlock(previous, width, stride, groups),
                PackedBasicBlock(width, width, 1, groups),
            ]
            stages.append(nn.Sequential(*blocks))
            previous = width
        self.layer1, self.layer2, self.layer3, self.layer4 = stages

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = functional.max_pool2d(functional.relu(self.bn1(self.conv1(x))), 3, 2, 1)
        x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
        return torch.flatten(functional.adaptive_avg_pool2d(x, 1), 1)


class GroupedLinear(nn.Module):
    """``members`` independent linear layers side by side: ``(N, members * in_features)``
    to ``(N, members * out_features)``, member ``m``'s block through member ``m``'s
    weights."""

    def __init__(self, members: int, in_features: int, out_features: int) -> None:
        super().__init__()
        self.members, self.in_features, self.out_features = members, in_features, out_features
        bound = 1.0 / math.sqrt(in_features)  # nn.Linear's initialisation, per member
        self.weight = nn.Parameter(
            torch.empty(members, in_features, out_features).uniform_(-bound, bound)
        )
        self.bias = nn.Parameter(torch.empty(members, 1, out_features).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        per_member = x.reshape(len(x), self.members, self.in_features).transpose(0, 1)
        out = torch.baddbmm(self.bias, per_member, self.weight)  # (members, N, out)
        return out.transpose(0, 1).reshape(len(x), self.members * self.out_features)
