"""A prediction's inputs onto the device in one copy, and its results back in one.

On a GPU every host-to-device copy and every device-to-host read costs a round trip (an
ensemble that read each member's four results back separately spent more time waiting than
computing). :func:`upload` packs a frame's inputs (the image, the velocities, the dropout
masks drawn on the CPU) into one buffer, pinned on CUDA, copies it once and views the parts
back out on the device; :func:`download` flattens the results into one float32 tensor,
reads it back once (the one synchronisation) and splits it into arrays. On the CPU nothing
is copied to upload; the download is the same one read.
"""

from __future__ import annotations

import numpy as np
import torch

#: Each part of an upload starts at a multiple of this many bytes (the widest dtype's
#: alignment), so that it can be viewed as its own dtype on the device.
ALIGNMENT_BYTES = 16


def upload(device: torch.device, *tensors: torch.Tensor) -> list[torch.Tensor]:
    """CPU ``tensors`` on ``device``, with one host-to-device copy of their bytes."""
    if device.type == "cpu":
        return list(tensors)
    packed = pack(tensors, pin_memory=True)
    return unpack(packed.to(device, non_blocking=True), tensors)


def pack(tensors: tuple[torch.Tensor, ...], pin_memory: bool = False) -> torch.Tensor:
    """``tensors``' bytes in one uint8 buffer, each part aligned (see :func:`unpack`)."""
    starts = _starts(tensors)
    packed = torch.empty(int(starts[-1]), dtype=torch.uint8, pin_memory=pin_memory)
    for tensor, start in zip(tensors, starts, strict=False):
        flat = tensor.contiguous().reshape(-1).view(torch.uint8)
        packed[start : start + len(flat)] = flat
    return packed


def unpack(packed: torch.Tensor, like: tuple[torch.Tensor, ...]) -> list[torch.Tensor]:
    """The tensors :func:`pack` packed, viewed out of ``packed`` (on any device) with the
    dtypes and shapes of ``like``."""
    return [
        packed[start : start + tensor.numel() * tensor.element_size()]
        .view(tensor.dtype)
        .reshape(tensor.shape)
        for tensor, start in zip(like, _starts(like), strict=False)
    ]


def _starts(tensors: tuple[torch.Tensor, ...]) -> np.ndarray:
    """Where each tensor's bytes start in a packed buffer, and (last) the buffer's size."""
    sizes = [tensor.numel() * tensor.element_size() for tensor in tensors]
    aligned = [-(-size // ALIGNMENT_BYTES) * ALIGNMENT_BYTES for size in sizes]
    return np.cumsum([0, *aligned])


def download(*tensors: torch.Tensor) -> list[np.ndarray]:
    """``tensors`` (any device and float dtype) as float32 arrays, with one device-to-host
    read."""
    flat = torch.cat([tensor.detach().reshape(-1).float() for tensor in tensors])
    values = flat.cpu().numpy()
    sizes = np.cumsum([0, *(tensor.numel() for tensor in tensors)])
    return [
        values[start:end].reshape(tuple(tensor.shape))
        for tensor, start, end in zip(tensors, sizes[:-1], sizes[1:], strict=True)
    ]
