"""Plots of training: loss curves, and predicted against true state along a lap."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from saferace.eval.track_plots import legend_outside, plt
from saferace.learning.networks import STATE_OUTPUTS, Prediction
from saferace.learning.rounds import FrameSet

STATE_LABELS = {
    "e_y_m": "lateral offset e_y [m]",
    "e_psi_rad": "heading error e_psi [rad]",
    "kappa_radpm": "curvature kappa [1/m]",
}


def plot_losses(history: dict[str, dict[str, list[float]]], path: str | Path) -> None:
    """Per network: the loss of every batch, and each epoch's training and validation loss
    at the step it ended, with the epoch an early stop kept; one legend below the plots.
    A heteroscedastic network trains on the Gaussian negative log-likelihood, which goes
    below 0: its training losses get a linear axis, its held-out MSE one of its own."""
    fig, axes = plt.subplots(
        1, len(history), figsize=(6 * len(history), 4.4), squeeze=False, layout="constrained"
    )
    owners = []
    for ax, (name, losses) in zip(axes[0], history.items(), strict=True):
        batches = np.asarray(losses["batch_loss"])
        likelihood = bool(len(batches)) and float(batches.min()) <= 0.0
        ax.plot(np.arange(1, len(batches) + 1), batches, color="0.75", lw=0.6, label="batch")
        epoch_ends = losses["epoch_end_step"]
        ax.plot(epoch_ends, losses["train_loss"], "o-", label="training epoch")
        held_out = ax.twinx() if likelihood else ax
        if losses["val_loss"]:
            held_out.plot(
                epoch_ends, losses["val_loss"], "s-", color="C1", label="held-out stretch"
            )
        for best in losses.get("best_epoch", []):
            kept = epoch_ends[int(best) - 1]
            ax.axvline(kept, color="k", ls=":", label="epoch kept (early stop)")
        held_out.set_yscale("log")
        ax.set_yscale("linear" if likelihood else "log")
        ax.set_xlabel("gradient step")
        ax.set_ylabel("Gaussian NLL" if likelihood else "MSE of normalised targets")
        if likelihood:
            held_out.set_ylabel("held-out MSE of normalised means")
        ax.set_title(f"{name} network")
        ax.grid(alpha=0.3, which="both")
        owners += [ax, held_out] if likelihood else [ax]
    legend_outside(fig, owners, ncol=4, fontsize=9)  # below the plots, off the curves
    fig.savefig(path, dpi=110)
    plt.close(fig)


def first_lap(frames: FrameSet) -> np.ndarray:
    """Indices of the first episode's first lap (until ``s`` wraps round)."""
    episode = np.flatnonzero(
        (frames["episode"] == frames["episode"][0]) & (frames["source"] == frames["source"][0])
    )
    s = frames["s_m"][episode]
    wraps = np.flatnonzero(np.diff(s) < -0.5 * frames["track_length_m"][0])
    return episode[: wraps[0] + 1] if len(wraps) else episode


def plot_state_along_lap(
    frames: FrameSet,
    prediction: Prediction,
    path: str | Path,
    title: str,
    stretch: tuple[float, float] | None = None,
) -> None:
    """True state and the state network's mean with a band of two MC-dropout spreads,
    against ``s`` over the first lap; ``stretch`` (fractions of the lap) is shaded; the
    legend below the plots."""
    lap = first_lap(frames)
    s = frames["s_m"][lap]
    fig, axes = plt.subplots(
        len(STATE_OUTPUTS), 1, figsize=(11, 8.5), sharex=True, layout="constrained"
    )
    for column, (ax, name) in enumerate(zip(axes, STATE_OUTPUTS, strict=True)):
        mean, std = prediction.mean[lap, column], prediction.std[lap, column]
        ax.fill_between(
            s,
            mean - 2 * std,
            mean + 2 * std,
            color="tab:blue",
            alpha=0.25,
            label="state network +- 2 MC-dropout spreads",
        )
        ax.plot(s, mean, color="tab:blue", lw=1.2, label="state network (MC mean)")
        ax.plot(s, frames["state"][lap, column], color="k", lw=1.2, label="true")
        if stretch is not None:
            length = float(frames["track_length_m"][0])
            ax.axvspan(
                stretch[0] * length,
                stretch[1] * length,
                color="tab:orange",
                alpha=0.15,
                label="held out of training",
            )
        ax.set_ylabel(STATE_LABELS[name])
        ax.grid(alpha=0.3)
    axes[0].set_title(title)
    axes[-1].set_xlabel("centerline arc length s [m]")
    legend_outside(fig, axes[:1], ncol=4, fontsize=9)  # below the plots, off the lines
    fig.savefig(path, dpi=110)
    plt.close(fig)
