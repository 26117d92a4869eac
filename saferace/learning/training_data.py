"""What a network trains on: its images, velocities and targets, and its batches.

A batch's images are redrawn by photometric augmentation (``saferace.learning.augmentation``)
and, where the data may be mirrored (a perception model's mono frames), half of them are
flipped left for right with their states negated: a lopsided track or a run of left bends
in the training tracks teaches no side.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from saferace.errors import SafeRaceError
from saferace.learning.augmentation import photometric
from saferace.learning.networks import DrivingNetwork
from saferace.learning.rounds import FrameSet


@dataclass(frozen=True)
class NetworkData:
    """What one network trains on: images, velocities (or None), targets, and where the
    frames may be mirrored left for right in training, the targets of the mirrored frames
    (:func:`mirrored_state`)."""

    images: np.ndarray
    velocity: np.ndarray | None
    targets: np.ndarray
    mirrored_targets: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.targets)


def held_out_mask(frames: FrameSet, stretch: tuple[float, float] | None) -> np.ndarray:
    """Frames whose position on the lap lies in ``[start, end)`` of the lap (none: None)."""
    if stretch is None:
        return np.zeros(len(frames), bool)
    fraction = frames.lap_fraction
    return (fraction >= stretch[0]) & (fraction < stretch[1])


def network_data(frames: FrameSet, mirror: bool = False) -> dict[str, NetworkData]:
    """Inputs and targets of the control and the state network; with ``mirror``, the
    state network's frames may be mirrored in training (mono images only)."""
    if mirror and frames["image"].shape[-1] != 3:
        raise SafeRaceError("only mono images can be mirrored (a stereo pair swaps its views)")
    state = frames["state"]
    mirrored = mirrored_state(state) if mirror else None
    return {
        "control": NetworkData(frames["image"], frames["velocity"], frames["expert"][:, :2]),
        "state": NetworkData(frames["image"], None, state, mirrored),
    }


def mirrored_state(state: np.ndarray) -> np.ndarray:
    """``[e_y, e_psi, kappa]`` of the mirror image of each frame: a car left of its lane's
    centre, heading left, in a left bend, seen in a mirror is right of it, heading right,
    in a right bend (the onboard camera sits on the car's axis, the lane lines are alike)."""
    return -state


def mirror_draw(
    data: NetworkData, index: np.ndarray, augmenter: torch.Generator | None
) -> torch.Tensor | None:
    """Which frames of ``index`` to mirror (half of them, drawn from ``augmenter``), where
    ``data`` may be mirrored and the images are augmented; None where not."""
    if augmenter is None or data.mirrored_targets is None:
        return None
    return torch.rand(index.shape, generator=augmenter) < 0.5


def network_outputs(
    network: DrivingNetwork,
    data: NetworkData,
    index: np.ndarray,
    augmenter: torch.Generator | None = None,
    flipped: torch.Tensor | None = None,
) -> torch.Tensor:
    """The network's outputs for frames ``index``, their images augmented with draws from
    ``augmenter`` where one is given, and mirrored left for right where ``flipped``. A
    ``(K, B)`` index gives a MIMO network's K subnetworks each its own frames, side by side
    in the channels."""
    velocity = None if data.velocity is None else torch.from_numpy(data.velocity[index])
    images = torch.from_numpy(data.images[index.reshape(-1)])
    if flipped is not None:
        mask = flipped.reshape(-1)
        images[mask] = images[mask].flip(2)
    if augmenter is not None:
        images = photometric(images, augmenter)
    if index.ndim == 2:  # (K B, H, W, C) -> (B, H, W, K C)
        subnetworks, batch = index.shape
        images = images.reshape(subnetworks, batch, *images.shape[1:]).permute(1, 2, 3, 0, 4)
        images = images.reshape(*images.shape[:3], -1)
    return network(images, velocity)
