"""Collection rounds on disk: one folder per round, written atomically, with a manifest.

A dataset folder holds ``round_0000/``, ``round_0001/``, ... Each round is one collection
run (one driver, track and task; one episode per seed): ``frames.npz`` (compressed arrays,
one row per control step, see :data:`FRAME_FIELDS`) and ``manifest.json`` (the collection's
configuration, versions, frame count). A round is written into a hidden ``.partial-*``
folder and renamed into place only when complete and synced, so a process killed at any
moment leaves every earlier round readable and no half-written round under a round's name.
:func:`load_rounds` aggregates any set of rounds or dataset folders.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import uuid
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from saferace.errors import SafeRaceError
from saferace.names import MANIFEST_FILE

LOG = logging.getLogger(__name__)

#: Per-frame arrays of a round: dtype and the shape of one frame (``None``: the image's).
FRAME_FIELDS: dict[str, tuple[str, tuple[int, ...] | None]] = {
    "image": ("uint8", None),  # (H, W, 3) mono or (H, W, 6) stereo
    "velocity": ("float32", (3,)),  # measured [v_x_mps, v_y_mps, yaw_rate_radps]
    "driver_action": ("float32", (2,)),  # the driver's [steer_rad, accel_mps2], with noise
    "applied_action": ("float32", (2,)),  # what the car got (after a filter)
    "expert": ("float32", (3,)),  # the expert's [steer_rad, target_speed_mps, accel_mps2]
    "state": ("float32", (3,)),  # true [e_y_m, e_psi_rad, kappa_radpm]
    "s_m": ("float32", ()),  # centerline arc length
    "time_s": ("float32", ()),  # since the episode's start
    "episode": ("int32", ()),  # which episode of the round (one per seed)
    "intervened": ("bool", ()),  # the safety filter changed the driver's action
}
FRAMES_FILE = "frames.npz"
#: Frames a round keeps apart: driven, never trained on (DAgger's part of the lap past its
#: ``train_fraction``), for scoring and calibrating the networks.
HELD_OUT_FILE = "held_out.npz"
ROUND_NAME = re.compile(r"^round_(\d{4,})$")
PARTIAL_PREFIX = ".partial-"
FORMAT_VERSION = 1


@dataclass
class FrameSet:
    """Frames of one or more rounds as aligned arrays: :data:`FRAME_FIELDS`, and from each
    round's manifest ``round`` (its number in its dataset), ``source`` (its index in
    ``manifests``, unique), ``track``, ``task`` and ``track_length_m``."""

    arrays: dict[str, np.ndarray]
    manifests: list[dict]

    def __len__(self) -> int:
        return len(self.arrays["s_m"])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]

    def subset(self, mask: np.ndarray) -> FrameSet:
        """The frames where ``mask`` (boolean or indices) selects."""
        return FrameSet({k: v[mask] for k, v in self.arrays.items()}, self.manifests)

    @property
    def lap_fraction(self) -> np.ndarray:
        """``s / track length`` of every frame, in ``[0, 1)``."""
        return np.mod(self["s_m"] / self["track_length_m"], 1.0)


def write_round(
    dataset_dir: str | Path,
    arrays: dict[str, np.ndarray],
    config: dict,
    held_out: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write one round atomically as the next ``round_NNNN`` of ``dataset_dir``; its path.

    ``held_out``: frames to keep apart from the training frames (none: no such file).
    """
    dataset_dir = Path(dataset_dir)
    arrays = _checked_frames(arrays)
    held_out_count = 0 if held_out is None else len(held_out["s_m"])
    held_out = _checked_frames(held_out) if held_out is not None and held_out_count else None
    dataset_dir.mkdir(parents=True, exist_ok=True)
    _remove_abandoned_partials(dataset_dir)
    partial = dataset_dir / f"{PARTIAL_PREFIX}{os.getpid()}-{uuid.uuid4().hex[:8]}"
    partial.mkdir()
    try:
        # Any: mypy cannot tell the arrays' names from savez's allow_pickle keyword.
        parts: tuple[tuple[str, dict[str, Any] | None], ...] = (
            (FRAMES_FILE, arrays),
            (HELD_OUT_FILE, held_out),
        )
        for name, part in parts:
            if part is None:
                continue
            with open(partial / name, "wb") as handle:
                np.savez_compressed(handle, **part)
                handle.flush()
                os.fsync(handle.fileno())
        manifest = {
            "format": FORMAT_VERSION,
            "frame_count": len(arrays["s_m"]),
            "held_out_frame_count": held_out_count,
            "image_shape": list(arrays["image"].shape[1:]),
            "config": config,
        }
        with open(partial / MANIFEST_FILE, "w") as handle:
            json.dump(manifest, handle, indent=2)
            handle.flush()
            os.fsync(handle.fileno())
        _fsync_dir(partial)
    except BaseException:  # an interrupted write (Ctrl-C, full disk) leaves nothing behind
        shutil.rmtree(partial, ignore_errors=True)
        raise
    while True:
        target = dataset_dir / f"round_{next_round_index(dataset_dir):04d}"
        try:
            os.rename(partial, target)  # atomic; fails if a concurrent writer took the name
        except OSError:
            if not target.exists():
                raise
            continue
        _fsync_dir(dataset_dir)
        return target


def next_round_index(dataset_dir: str | Path) -> int:
    """One more than the highest round number in use (0 for none); a damaged round folder
    without a manifest keeps its number too."""
    dataset_dir = Path(dataset_dir)
    names = (p.name for p in dataset_dir.iterdir()) if dataset_dir.is_dir() else ()
    numbers = [int(match.group(1)) for name in names if (match := ROUND_NAME.match(name))]
    return max(numbers, default=-1) + 1


def round_dirs(path: str | Path) -> list[Path]:
    """The complete rounds at ``path``: the round itself, or those in a dataset folder."""
    path = Path(path)
    if ROUND_NAME.match(path.name) and (path / MANIFEST_FILE).is_file():
        return [path]
    if not path.is_dir():
        return []
    return sorted(
        (p for p in path.iterdir() if ROUND_NAME.match(p.name) and (p / MANIFEST_FILE).is_file()),
        key=_round_number,
    )


def load_rounds(paths: Iterable[str | Path], held_out: bool = False) -> FrameSet:
    """All frames of the rounds at ``paths`` (round folders or dataset folders), in order;
    ``held_out=True``: their held-out frames instead (a round without any adds none)."""
    rounds: list[Path] = []
    for path in paths:
        found = round_dirs(path)
        if not found:
            raise SafeRaceError(
                f"no complete collection round at {path}: expected a dataset folder with "
                "round_NNNN/ folders or one round folder (write them with saferace collect)"
            )
        rounds += [p.resolve() for p in found if p.resolve() not in rounds]
    parts: list[dict[str, np.ndarray]] = []
    manifests = []
    file_name, count_key = (
        (HELD_OUT_FILE, "held_out_frame_count") if held_out else (FRAMES_FILE, "frame_count")
    )
    for source, path in enumerate(rounds):
        manifest = json.loads((path / MANIFEST_FILE).read_text())
        if manifest["format"] > FORMAT_VERSION:
            raise SafeRaceError(
                f"{path} is a round of format {manifest['format']}; this SafeRace reads up to "
                f"{FORMAT_VERSION}: upgrade SafeRace"
            )
        manifests.append({**manifest, "path": str(path)})
        expected = manifest.get(count_key, 0)
        if not expected:
            continue
        with np.load(path / file_name) as stored:
            frames = {name: stored[name] for name in FRAME_FIELDS}
        count = len(frames["s_m"])
        if count != expected:
            raise SafeRaceError(f"{path / file_name} holds {count} frames, its manifest {expected}")
        config = manifest["config"]
        frames["round"] = np.full(count, _round_number(path), np.int32)
        frames["source"] = np.full(count, source, np.int32)
        frames["track"] = np.full(count, config["track"])
        frames["task"] = np.full(count, config["task"])
        frames["track_length_m"] = np.full(count, config["track_length_m"], np.float32)
        parts.append(frames)
    shapes = {tuple(m["image_shape"]) for m in manifests}
    if len(shapes) > 1:
        raise SafeRaceError(
            f"rounds with different image shapes cannot be mixed: {sorted(shapes)} "
            f"(mono and stereo, or different --image-size)"
        )
    if not parts:
        raise SafeRaceError(
            f"the rounds at {', '.join(map(str, paths))} hold no held-out frames (a drive "
            "keeps some only when it passes the train fraction of the lap)"
        )
    arrays = {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}
    return FrameSet(arrays, manifests)


def round_episodes(round_dir: str | Path) -> tuple[dict, list[dict[str, np.ndarray]]]:
    """A round's manifest and its episodes as driven: each episode's frames, training and
    held-out together, in time order."""
    round_dir = Path(round_dir)
    manifest = json.loads((round_dir / MANIFEST_FILE).read_text())
    parts = []
    for name, count_key in ((FRAMES_FILE, "frame_count"), (HELD_OUT_FILE, "held_out_frame_count")):
        if manifest.get(count_key, 0):
            with np.load(round_dir / name) as stored:
                parts.append({field: stored[field] for field in FRAME_FIELDS})
    frames = {field: np.concatenate([part[field] for part in parts]) for field in FRAME_FIELDS}
    episodes = []
    for episode in np.unique(frames["episode"]):
        rows = np.flatnonzero(frames["episode"] == episode)
        rows = rows[np.argsort(frames["time_s"][rows], kind="stable")]
        episodes.append({field: values[rows] for field, values in frames.items()})
    return manifest, episodes


def _checked_frames(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    missing = set(FRAME_FIELDS) - set(arrays)
    if missing:
        raise SafeRaceError(f"a round needs the arrays {sorted(missing)}")
    count = len(arrays["s_m"])
    if count == 0:
        raise SafeRaceError("a round needs at least one frame")
    checked = {}
    for name, (dtype, shape) in FRAME_FIELDS.items():
        values = np.asarray(arrays[name], dtype=dtype)
        expected = values.shape[1:] if shape is None else shape
        if values.shape != (count, *expected) or (shape is None and values.ndim != 4):
            raise SafeRaceError(
                f"round array {name!r} has shape {values.shape}, expected ({count}, ...)"
            )
        checked[name] = values
    return checked


def _round_number(path: Path) -> int:
    match = ROUND_NAME.match(path.name)
    assert match is not None, f"{path} is not a round folder"  # callers pass only those
    return int(match.group(1))


def _remove_abandoned_partials(dataset_dir: Path) -> None:
    """Delete half-written rounds whose writer process no longer runs."""
    for partial in dataset_dir.glob(f"{PARTIAL_PREFIX}*"):
        pid = partial.name[len(PARTIAL_PREFIX) :].split("-")[0]
        if pid.isdigit() and not _process_alive(int(pid)):
            LOG.warning("removing %s, a round left unfinished by an interrupted writer", partial)
            shutil.rmtree(partial, ignore_errors=True)


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _fsync_dir(path: Path) -> None:
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)
