"""Checkpoints of the learned driver: both networks, their normalisation and their training.

One file holds the control network (none in a perception model, which only perceives) and
the state network or ensemble (weights with their
normalisation buffers, and each one's :class:`~saferace.learning.networks.NetworkConfig`)
and metadata: the training configuration, the data rounds' manifests, the loss history of
each network trained (one kept unchanged is named with its source), the validation table,
the git revision and package versions. It is written to a temporary
file and renamed into place, so an interrupted save never leaves a truncated checkpoint,
and it loads with ``torch.load(weights_only=True)``: plain data only, no pickled code.
"""

from __future__ import annotations

import hashlib
import io
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import torch

from saferace.errors import SafeRaceError
from saferace.learning.device import resolve_device
from saferace.learning.ensemble import StateEnsemble, StateNetwork
from saferace.learning.networks import DrivingNetwork, NetworkConfig

FORMAT = "saferace-learned-driver"
FORMAT_VERSION = 1
NETWORK_NAMES = ("control", "state")
#: The metadata entry of the state network's conformal calibration
#: (:class:`~saferace.safety.uncertainty.conformal.ConformalCalibration` as a dict), if it has one.
CONFORMAL_KEY = "conformal"


@dataclass
class LearnedCheckpoint:
    """The two networks (in eval mode; ``control`` None in a perception model) and the
    checkpoint's metadata."""

    control: DrivingNetwork | None
    state: StateNetwork
    metadata: dict
    path: Path | None = None
    sha256: str | None = None

    def networks(self) -> dict[str, StateNetwork]:
        """The networks it holds by name (no ``control`` in a perception model)."""
        named = zip(NETWORK_NAMES, (self.control, self.state), strict=True)
        return {name: network for name, network in named if network is not None}

    def describe(self) -> dict:
        """What a result row records of this checkpoint."""
        return {"path": str(self.path), "sha256": self.sha256}


def save_checkpoint(
    path: str | Path, control: DrivingNetwork | None, state: StateNetwork, metadata: dict
) -> Path:
    """Write both networks (or the state network alone) and ``metadata`` to ``path``
    atomically."""
    payload = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "networks": {
            name: _entry(network)
            for name, network in zip(NETWORK_NAMES, (control, state), strict=True)
            if network is not None
        },
        "metadata": metadata,
    }
    return save_atomically(payload, path)


def _entry(network: StateNetwork) -> dict:
    """A network's config and weights, on the CPU from any device (an ensemble's: each
    member's)."""
    if isinstance(network, StateEnsemble):
        return {"members": [_entry(member) for member in network.members]}
    weights = {name: tensor.cpu() for name, tensor in network.state_dict().items()}
    return {"config": network.config.as_dict(), "weights": weights}


def save_with_metadata(source: str | Path, metadata: dict, out: str | Path) -> Path:
    """Write ``source``'s networks with ``metadata`` merged into its own to ``out``
    atomically (``out`` may be ``source``)."""
    loaded = load_checkpoint(source)
    return save_checkpoint(out, loaded.control, loaded.state, {**loaded.metadata, **metadata})


def save_atomically(payload: dict, path: str | Path) -> Path:
    """``torch.save`` to a temporary file beside ``path``, synced, then renamed into place."""
    return _write_atomically(path, lambda handle: torch.save(payload, handle))


def write_text_atomically(path: str | Path, text: str) -> Path:
    """Write ``text`` as :func:`save_atomically` writes a checkpoint."""
    return _write_atomically(path, lambda handle: handle.write(text.encode()))


def _write_atomically(path: str | Path, write: Callable[[BinaryIO], object]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        with open(temporary, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path


def is_calibrated(path: str | Path) -> bool:
    """Whether the checkpoint at ``path`` holds a conformal calibration of its state network."""
    return CONFORMAL_KEY in load_checkpoint(path).metadata


def load_checkpoint(
    path: str | Path, device: str | torch.device | None = None
) -> LearnedCheckpoint:
    """Both networks of a checkpoint written by :func:`save_checkpoint`, ready to predict on
    ``device`` (see :func:`~saferace.learning.device.resolve_device`), whatever device they
    were saved from."""
    path = Path(path)
    if not path.is_file():
        raise SafeRaceError(f"no checkpoint at {path}: train one with saferace train ... --out")
    raw = path.read_bytes()  # read once: the hash and the weights are of the same bytes
    try:
        payload = torch.load(io.BytesIO(raw), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many kinds for a file that is not a checkpoint
        raise SafeRaceError(f"{path} is not a SafeRace checkpoint: {exc}") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise SafeRaceError(f"{path} is not a SafeRace checkpoint (written by saferace train)")
    if payload["version"] > FORMAT_VERSION:
        raise SafeRaceError(
            f"{path} has checkpoint format {payload['version']}; this SafeRace reads up to "
            f"{FORMAT_VERSION}: upgrade SafeRace"
        )
    try:
        networks = payload["networks"]
        control = _single_network(networks["control"]) if "control" in networks else None
        state = _network(networks["state"])
    except (KeyError, RuntimeError, TypeError) as exc:
        raise SafeRaceError(f"{path} holds damaged or mismatched networks: {exc}") from None
    sha256 = hashlib.sha256(raw).hexdigest()
    target = resolve_device(device)
    if control is not None:
        control.to(target)
    state.to(target)
    return LearnedCheckpoint(control, state, payload["metadata"], path, sha256)


def _network(entry: dict) -> StateNetwork:
    if "members" in entry:
        return StateEnsemble([_single_network(member) for member in entry["members"]])
    return _single_network(entry)


def _single_network(entry: dict) -> DrivingNetwork:
    """The network of ``entry``, its tensors the loaded ones: built without weights (on the
    meta device), since drawing a ResNet-18's random ones to overwrite took 90 ms."""
    with torch.device("meta"):
        network = DrivingNetwork(NetworkConfig.from_dict(entry["config"]))
    network.load_state_dict(entry["weights"], assign=True)
    network.eval()
    return network.to(memory_format=torch.channels_last)
