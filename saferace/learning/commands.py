"""What ``saferace train``, ``validate`` and ``gradcam`` do: train or load, score, plot, write.

``train`` keeps its progress in ``NAME.resume.pt`` (an interrupted run started again
continues from its last epoch) and writes, next to the checkpoint ``NAME.pt``,
``NAME_loss.png`` (loss curves), ``NAME_validation.md`` and ``.csv`` (errors and MC-dropout
spreads on the training frames, the held-out stretch and its near and far halves) and
``NAME_state_along_lap.png`` (the state network along the first lap, held-out stretch
shaded). ``validate`` writes the same
table and one state plot per data set for a checkpoint on rounds it may never have seen.
``gradcam`` lets the expert lap a track and writes GradCAM sheets of frames spread over it.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

from saferace.errors import SafeRaceError
from saferace.eval.agents import make_agent
from saferace.eval.runner import run_episode, task_id
from saferace.learning.agent import check_image_shape
from saferace.learning.checkpoint import load_checkpoint, save_checkpoint
from saferace.learning.ensemble import StateEnsemble
from saferace.learning.plots import first_lap, plot_losses, plot_state_along_lap
from saferace.learning.rounds import FrameSet, load_rounds
from saferace.learning.training import TrainConfig, train_networks
from saferace.learning.training_data import held_out_mask, network_data
from saferace.learning.validation import (
    predict_frames,
    scored_training_frames,
    validation_markdown,
    validation_rows,
)

HELD_OUT = "held-out stretch"


@dataclass(frozen=True)
class Report:
    """The files a command wrote and its validation rows."""

    files: list[Path]
    rows: list[dict]


def train_and_report(
    data_paths: list[str | Path],
    out: str | Path,
    config: TrainConfig,
    mc_samples: int = 10,
    require_stereo: bool = False,
    progress: bool = True,
) -> Report:
    """Train both networks on the rounds at ``data_paths``, score them, write everything.

    ``require_stereo``: refuse mono rounds (the command line's ``--stereo``).
    """
    out = Path(out)
    if mc_samples < 1:
        raise SafeRaceError(f"mc_samples must be at least 1, got {mc_samples}")
    frames = load_rounds(data_paths)
    if require_stereo and frames["image"].shape[-1] != 6:
        raise SafeRaceError(
            f"--stereo asks for stereo rounds, but {data_paths} hold mono images: collect "
            "them with saferace collect --stereo"
        )
    resume_file = out.with_suffix(".resume.pt")
    control, state, metadata = train_networks(frames, config, progress, resume_file)
    held_out = held_out_mask(frames, config.val_stretch)
    training = frames.subset(~held_out)
    splits = {
        "training": scored_training_frames(training, config.seed),
        HELD_OUT: frames.subset(held_out),
    }
    assert control is not None, "saferace train trains both networks"
    networks = {"control": control, "state": state}
    rows, _ = validation_rows(networks, splits, training, HELD_OUT, mc_samples, config.seed)
    metadata["validation"] = rows
    save_checkpoint(out, control, state, metadata)
    resume_file.unlink(missing_ok=True)

    stem = out.with_suffix("")
    loss_plot = stem.with_name(f"{stem.name}_loss.png")
    plot_losses(metadata["history"], loss_plot)
    lap = frames.subset(first_lap(frames))
    lap_plot = stem.with_name(f"{stem.name}_state_along_lap.png")
    plot_state_along_lap(
        lap,
        predict_frames(state, network_data(lap)["state"], mc_samples, seed=config.seed),
        lap_plot,
        f"state network on {lap['track'][0]}, first lap of round {lap['round'][0]}",
        config.val_stretch,
    )
    tables = write_table(rows, stem.with_name(f"{stem.name}_validation"))
    return Report([out, loss_plot, lap_plot, *tables], rows)


def validate_checkpoint(
    checkpoint: str | Path,
    data_paths: list[str | Path],
    out_dir: str | Path,
    mc_samples: int = 10,
    seed: int = 0,
) -> Report:
    """Score a checkpoint's networks on each data set (e.g. a track it never saw)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    loaded = load_checkpoint(checkpoint)
    splits: dict[str, FrameSet] = {}
    for path in data_paths:
        frames = load_rounds([path])
        check_image_shape(loaded, frames["image"].shape[1:])
        splits[f"{frames['track'][0]} {frames['task'][0]} ({path})"] = frames
    networks = loaded.networks()
    rows, predictions = validation_rows(networks, splits, n_samples=mc_samples, seed=seed)
    files = write_table(rows, out_dir / "validation")
    for index, (split, frames) in enumerate(splits.items()):
        path = out_dir / f"state_along_lap_{index}_{frames['track'][0]}.png"
        plot_state_along_lap(
            frames, predictions[split]["state"], path, f"state network on {split}, first lap"
        )
        files.append(path)
    return Report(files, rows)


def write_table(rows: list[dict], stem: Path) -> list[Path]:
    """``stem.md`` and ``stem.csv`` of validation rows."""
    markdown, table = stem.with_suffix(".md"), stem.with_suffix(".csv")
    markdown.write_text(validation_markdown(rows) + "\n")
    with open(table, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return [markdown, table]


def gradcam_report(
    checkpoint: str | Path,
    track: str,
    out_dir: str | Path,
    task: str = "CenterLine",
    frames: int = 6,
    layer: str = "layer2",
) -> Report:
    """GradCAM sheets of ``frames`` frames spread over one expert lap of ``track``."""
    loaded = load_checkpoint(checkpoint)
    height, width, channels = loaded.metadata["image_shape"]
    env = gym.make(task_id(task), track=track, image_size=(height, width), stereo=channels == 6)
    observations: list[dict] = []
    try:
        run_episode(
            env,
            make_agent("expert", env),
            seed=0,
            on_step=lambda observation, info, action: observations.append(observation),
        )
    finally:
        env.close()
    from saferace.learning.gradcam import gradcam_sheet, write_sheet  # captum only here

    state = loaded.state.members[0] if isinstance(loaded.state, StateEnsemble) else loaded.state
    networks = (  # an ensemble's first member
        {"state": state} if loaded.control is None else {"control": loaded.control, "state": state}
    )
    chosen = np.linspace(0, len(observations) - 1, frames).round().astype(int)
    files = []
    for number, index in enumerate(chosen):
        observation = observations[index]
        sheet = gradcam_sheet(networks, observation["image"], observation["velocity"], layer)
        files.append(write_sheet(Path(out_dir) / f"gradcam_{number:02d}_step{index}.png", sheet))
    return Report(files, [])
