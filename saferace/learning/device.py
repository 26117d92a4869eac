"""Which torch device the networks train and predict on.

``--device auto|cpu|cuda|cuda:N`` on every command that runs a network: ``auto`` takes a
GPU where PyTorch sees one, else the CPU. The command line puts its choice into
:data:`DEVICE_VARIABLE`, so that worker processes and Ray tasks it starts use it too; a
library user passes ``device=`` or sets the variable. On the CPU everything stays bit for
bit deterministic per seed. On CUDA the networks train under bfloat16 autocast, seeded but
not bitwise reproducible (cuDNN's convolution algorithms and atomics are not); MC-dropout
masks are still drawn on the CPU from the episode's seed. Checkpoints load on any device
(their weights are mapped to the CPU first).
"""

from __future__ import annotations

import contextlib
import os
import re

import torch

from saferace.errors import SafeRaceError
from saferace.names import DEVICE_HELP, DEVICE_VARIABLE


def resolve_device(spec: str | torch.device | None = None) -> torch.device:
    """The device ``spec`` names (default: :data:`DEVICE_VARIABLE`, else ``auto``); a
    :class:`SafeRaceError` naming the problem when it is not there."""
    if isinstance(spec, torch.device):
        return spec
    spec = spec or os.environ.get(DEVICE_VARIABLE) or "auto"
    if spec == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if spec == "cpu":
        return torch.device("cpu")
    match = re.fullmatch(r"cuda(?::(\d+))?", spec)
    if match is None:
        raise SafeRaceError(f"--device {spec!r}: use {DEVICE_HELP}")
    if not torch.cuda.is_available():
        raise SafeRaceError(
            f"--device {spec}: PyTorch sees no CUDA GPU on this machine (a CPU-only build, no "
            "driver, or CUDA_VISIBLE_DEVICES empty); use --device cpu or auto"
        )
    index = int(match.group(1) or 0)
    count = torch.cuda.device_count()
    if index >= count:
        raise SafeRaceError(
            f"--device {spec}: PyTorch sees {count} CUDA GPU(s), cuda:0 to cuda:{count - 1}"
        )
    return torch.device("cuda", index)


def use_device(spec: str) -> torch.device:
    """Check ``spec`` and make it this process's and its workers' default device."""
    device = resolve_device(spec)
    os.environ[DEVICE_VARIABLE] = str(device)
    return device


def autocast(device: torch.device) -> contextlib.AbstractContextManager:
    """bfloat16 autocast on CUDA; nothing on the CPU, whose results stay exact."""
    if device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()
