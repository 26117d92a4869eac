"""Where a DAgger run keeps its rounds, checkpoints and metrics: one small class, one place.

::

    run.json                      the settings (a run with other settings is refused)
    data/round_NNNN/              iteration N's round (saferace.learning.rounds)
    checkpoints/iteration_NN.pt   the networks that drove iteration N
    checkpoints/iteration_NN.resume.pt
                                  the training of iteration N in progress
    checkpoints/iteration_NN.spread_scale.json
                                  their state network's calibration (calibrate_spread)
    metrics.jsonl, metrics.csv    one row per iteration, written as soon as it exists
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

from saferace.errors import SafeRaceError
from saferace.names import MANIFEST_FILE

CHECKPOINT_NAME = re.compile(r"^iteration_(\d+)\.pt$")


@dataclass(frozen=True)
class RunLayout:
    """The paths of a DAgger run in ``root``."""

    root: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    @property
    def run_file(self) -> Path:
        return self.root / "run.json"

    def stored_fingerprint(self) -> dict | None:
        """The settings ``run.json`` records (None: no run has claimed the folder)."""
        if not self.run_file.exists():
            return None
        return json.loads(self.run_file.read_text())["fingerprint"]

    @property
    def data_dir(self) -> Path:
        return self.root / "data"

    @property
    def checkpoint_dir(self) -> Path:
        return self.root / "checkpoints"

    @property
    def metrics_jsonl(self) -> Path:
        return self.root / "metrics.jsonl"

    @property
    def metrics_csv(self) -> Path:
        return self.root / "metrics.csv"

    def round(self, iteration: int) -> Path:
        return self.data_dir / f"round_{iteration:04d}"

    def manifest(self, iteration: int) -> Path:
        """The file whose presence says iteration ``iteration``'s round is complete."""
        return self.round(iteration) / MANIFEST_FILE

    def checkpoint(self, iteration: int) -> Path:
        return self.checkpoint_dir / f"iteration_{iteration:02d}.pt"

    def resume(self, iteration: int) -> Path:
        return self.checkpoint_dir / f"iteration_{iteration:02d}.resume.pt"

    def spread_scale(self, iteration: int) -> Path:
        return self.checkpoint_dir / f"iteration_{iteration:02d}.spread_scale.json"

    def final_checkpoint(self) -> Path:
        """The checkpoint that drove the run's last iteration."""
        checkpoints = sorted(
            path
            for path in self.checkpoint_dir.glob("iteration_*.pt")
            if CHECKPOINT_NAME.match(path.name)
        )
        if not checkpoints:
            raise SafeRaceError(f"{self.root} holds no trained checkpoint yet")
        return checkpoints[-1]
