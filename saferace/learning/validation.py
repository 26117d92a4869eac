"""How well the networks predict, and whether their MC-dropout spread knows when they are wrong.

For every split of frames (training frames, the held-out stretch, a track never seen) and
every output: the RMSE, the mean MC-dropout spread, the share of frames whose error is
within two spreads, and the rank correlation of spread and absolute error. The held-out
frames are also split in half by their distance from the training data (nearest training
frame in the standardised true state ``[e_y, e_psi, kappa, v_x]``): a spread that grows
from the near half to the far half is what the probabilistic filter relies on.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

from saferace.eval.tables import markdown_table
from saferace.learning.cpu_compile import eager_calls
from saferace.learning.ensemble import StateNetwork
from saferace.learning.networks import Prediction
from saferace.learning.rounds import FrameSet
from saferace.learning.training_data import NetworkData, network_data

TABLE_COLUMNS = (
    "split",
    "network",
    "output",
    "frames",
    "RMSE",
    "mean spread",
    "within 2 spreads",
    "rank corr. spread/error",
)
#: Training frames scored at most (a seeded sample): enough for the RMSE, and quick.
MAX_SCORED_TRAIN_FRAMES = 1000


def predict_frames(
    network: StateNetwork,
    data: NetworkData,
    n_samples: int = 10,
    batch_size: int = 64,
    seed: int = 0,
) -> Prediction:
    """MC-dropout predictions for every frame of ``data``, in batches (eagerly, the last
    too when it holds one frame)."""
    generator = torch.Generator().manual_seed(seed)
    parts = []
    with eager_calls():
        for start in range(0, len(data), batch_size):
            stop = min(start + batch_size, len(data))
            velocity = None if data.velocity is None else data.velocity[start:stop]
            parts.append(network.predict(data.images[start:stop], velocity, n_samples, generator))
    return Prediction(
        *(
            np.concatenate([getattr(p, name) for p in parts])
            for name in ("mean", "std", "samples", "features")
        )
    )


def error_rows(
    split: str, network_name: str, network: StateNetwork, prediction: Prediction, targets
) -> list[dict]:
    """One row per output of ``network`` on one split."""
    rows = []
    for column, output in enumerate(network.config.outputs):
        error = prediction.mean[:, column] - targets[:, column]
        spread = prediction.std[:, column]
        correlation = (
            float(spearmanr(spread, np.abs(error)).statistic)
            if len(error) > 2 and np.ptp(spread) > 0
            else None
        )
        rows.append(
            {
                "split": split,
                "network": network_name,
                "output": output,
                "frames": len(error),
                "rmse": float(np.sqrt(np.mean(error**2))),
                "mean_spread": float(spread.mean()),
                "within_2_spreads": float(np.mean(np.abs(error) <= 2.0 * spread)),
                "spread_error_correlation": correlation,
            }
        )
    return rows


def distance_to_training(training: FrameSet, frames: FrameSet) -> np.ndarray:
    """Distance of each frame to the nearest training frame in the standardised true state."""

    def states(frame_set: FrameSet) -> np.ndarray:
        return np.column_stack([frame_set["state"], frame_set["velocity"][:, :1]])

    reference = states(training)
    scale = np.maximum(reference.std(axis=0), 1e-6)
    return cKDTree(reference / scale).query(states(frames) / scale)[0]


def validation_rows(
    networks: dict[str, StateNetwork],
    splits: dict[str, FrameSet],
    training: FrameSet | None = None,
    held_out: str | None = None,
    n_samples: int = 10,
    seed: int = 0,
) -> tuple[list[dict], dict[str, dict[str, Prediction]]]:
    """Error rows of every network on every split (and the near and far halves of
    ``splits[held_out]`` when ``training`` is given); also the predictions by split."""
    rows: list[dict] = []
    predictions: dict[str, dict[str, Prediction]] = {}
    for split, frames in splits.items():
        if not len(frames):
            continue
        data = network_data(frames)
        predictions[split] = {
            name: predict_frames(network, data[name], n_samples, seed=seed)
            for name, network in networks.items()
        }
        parts = {split: np.ones(len(frames), bool)}
        if training is not None and split == held_out:
            distance = distance_to_training(training, frames)
            near = distance <= np.median(distance)
            parts |= {f"{split}: near half": near, f"{split}: far half": ~near}
        for part, mask in parts.items():
            for name, network in networks.items():
                prediction = _rows_of(predictions[split][name], mask)
                rows += error_rows(part, name, network, prediction, data[name].targets[mask])
    return rows, predictions


def _rows_of(prediction: Prediction, mask: np.ndarray) -> Prediction:
    return Prediction(
        prediction.mean[mask], prediction.std[mask], prediction.samples[mask],
        prediction.features[mask],
    )  # fmt: skip


def scored_training_frames(frames: FrameSet, seed: int = 0) -> FrameSet:
    """At most :data:`MAX_SCORED_TRAIN_FRAMES` training frames, a seeded sample in order."""
    if len(frames) <= MAX_SCORED_TRAIN_FRAMES:
        return frames
    rng = np.random.default_rng(seed)
    return frames.subset(np.sort(rng.choice(len(frames), MAX_SCORED_TRAIN_FRAMES, replace=False)))


def validation_markdown(rows: list[dict]) -> str:
    return markdown_table(
        TABLE_COLUMNS,
        [
            [
                row["split"],
                row["network"],
                row["output"],
                row["frames"],
                row["rmse"],
                row["mean_spread"],
                row["within_2_spreads"],
                "-" if row["spread_error_correlation"] is None else row["spread_error_correlation"],
            ]
            for row in rows
        ],
    )
