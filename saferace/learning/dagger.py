"""DAgger with and without the safety filter (paper Sec. 2.3 and 4, "Training cycle").

Iteration 0: the expert MPC drives one lap from ground truth and the frames are recorded.
Iteration ``i >= 1``: both networks are trained on the rounds of iterations ``0..i-1``
(fine-tuned from iteration ``i-1``'s weights, as the authors did, or from scratch), then the
control network drives from the camera and the velocities while the expert labels every
frame; the round joins the aggregate. A drive ends when the lap is done or the car has left
the lane (the task terminates it). With a filter the iterations after ``filter_from`` drive
through :class:`~saferace.safety.cbf.filter.SafetyFilter` fed the state network's MC-dropout
samples (the perceived state) or the truth. A filtered run forks from the unfiltered one:
it shares iterations ``0..filter_from`` with it, bit for bit (linked with ``fork_of``, or
recomputed: every stage is seeded and deterministic). With ``train_fraction < 1`` frames are
kept only on that first part of the lap, and each iteration is also scored on the rest.

A run lives in one folder (:class:`~saferace.learning.run_layout.RunLayout`). Every round and
checkpoint is written atomically and training keeps its progress per epoch, so a killed run
started again with the same settings continues where it stopped.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from saferace.errors import SafeRaceError
from saferace.eval.filters import FilterConfig
from saferace.learning.calibration import conformal_of, spread_scale_of
from saferace.learning.checkpoint import save_checkpoint
from saferace.learning.collect import collect_round
from saferace.learning.configs import (
    NETWORKS,
    CollectionConfig,
    DaggerConfig,
    Perturbation,
)
from saferace.learning.rounds import load_rounds
from saferace.learning.run_layout import RunLayout
from saferace.learning.training import train_networks
from saferace.names import CONFORMAL_ALPHA
from saferace.progress import Progress
from saferace.version import __version__

#: Columns of ``metrics.csv`` (the held-out part's are prefixed ``held_out_``).
METRIC_COLUMNS = (
    "iteration",
    "driver",
    "filtered",
    "completed",
    "lap_time_s",
    "duration_s",
    "mean_abs_deviation_m",
    "time_outside_lane_s",
    "longest_stop_s",
    "longest_standstill_s",
    "intervention_rate",
    "alarm_rate",
    "coverage",
    "at_fault_collisions",
    "overtakes",
    "spread_scale_e_y",
    "held_out_mean_abs_deviation_m",
    "held_out_time_outside_lane_s",
    "frames",
    "train_seconds",
    "collect_seconds",
)


class DaggerRun:
    """A DAgger run in its folder, round by round like imitation's ``DAggerTrainer``:
    :meth:`train_iteration` trains the networks that drive an iteration,
    :meth:`collect_iteration` drives it and writes its round and metrics, and :meth:`run`
    does whatever of iterations ``0..iterations`` is missing."""

    def __init__(
        self,
        out_dir: str | Path,
        config: DaggerConfig,
        fork_of: str | Path | None = None,
        progress: bool = True,
        label: str = "dagger",
        workers: int = 1,
        ray_address: str | None = None,
        num_envs: int = 1,
    ) -> None:
        """``workers``/``ray_address``/``num_envs``: where and how many of an iteration's
        episodes are driven at once (see :func:`~saferace.learning.collect.collect_round`);
        the rounds are the same."""
        self.workers, self.ray_address, self.num_envs = workers, ray_address, num_envs
        self.layout = RunLayout(Path(out_dir))
        self.config = config
        self.fork_of = None if fork_of is None else RunLayout(Path(fork_of))
        self.progress = progress
        self.label = label
        self._claim_folder()

    @property
    def out_dir(self) -> Path:
        return self.layout.root

    def metrics(self) -> list[dict]:
        """The iterations' metric rows written so far."""
        path = self.layout.metrics_jsonl
        if not path.exists():
            return []
        with open(path) as handle:
            return [json.loads(line) for line in handle if line.strip()]

    def done(self, iteration: int) -> bool:
        """Whether ``iteration`` has been trained, driven and recorded."""
        return any(row["iteration"] == iteration for row in self.metrics())

    # ------------------------------------------------------------------ rounds
    def run(self) -> list[dict]:
        """Every missing stage of iterations ``0..iterations``; all metric rows."""
        if self.fork_of is not None:
            self._link_shared_iterations()
        done = {row["iteration"] for row in self.metrics()}
        with Progress(
            self.config.iterations + 1,
            self.label,
            "iteration",
            enabled=self.progress,
            initial=len(done),
        ) as bar:
            for iteration in range(self.config.iterations + 1):
                if iteration in done:
                    continue
                train_seconds = None
                if iteration > 0 and not self.layout.checkpoint(iteration).exists():
                    bar.note(f"iteration {iteration}: training")
                    train_seconds = self.train_iteration(iteration)
                bar.note(f"iteration {iteration}: driving")
                rows = self.collect_iteration(iteration, train_seconds)
                bar.done(f"iteration {iteration}", iteration_words(rows[-1]))
        return self.metrics()

    def train_iteration(self, iteration: int) -> float:
        """Train the networks that drive ``iteration`` (>= 1) on rounds ``0..iteration-1``,
        resuming a training in progress; the seconds taken."""
        if iteration < 1:
            raise SafeRaceError("iteration 0 is the expert's: it has no networks to train")
        missing = [i for i in range(iteration) if not self.layout.manifest(i).exists()]
        if missing:
            raise SafeRaceError(f"iteration {iteration} trains on rounds {missing} not driven yet")
        started = time.perf_counter()
        config = self.config
        init = (
            self.layout.checkpoint(iteration - 1) if config.warm_start and iteration > 1 else None
        )
        training = replace(
            config.training,
            networks=NETWORKS if init is None else config.trained_networks,
            init=None if init is None else str(init),
        )
        rounds = [self.layout.round(i) for i in range(iteration)]
        resume_file = self.layout.resume(iteration)
        control, state, metadata = train_networks(
            load_rounds(rounds), training, self.progress, resume_file
        )
        metadata["dagger_iteration"] = iteration
        save_checkpoint(self.layout.checkpoint(iteration), control, state, metadata)
        resume_file.unlink(missing_ok=True)
        return time.perf_counter() - started

    def collect_iteration(self, iteration: int, train_seconds: float | None = None) -> list[dict]:
        """Drive ``iteration`` (unless its round exists) and append its metric row; all
        metric rows. ``train_seconds`` is recorded with it."""
        collect_seconds = None
        if not self.layout.manifest(iteration).exists():
            if iteration > 0 and not self.layout.checkpoint(iteration).exists():
                raise SafeRaceError(f"iteration {iteration} has no networks: train it first")
            started = time.perf_counter()
            self._drive(iteration)
            collect_seconds = time.perf_counter() - started
        if not self.done(iteration):
            self._append_metrics(
                iteration, {"train_seconds": train_seconds, "collect_seconds": collect_seconds}
            )
        return self.metrics()

    def iteration_filter(self, iteration: int) -> FilterConfig:
        """The filter ``iteration`` drives through (``kind="none"`` before the fork)."""
        config = self.config
        if not config.filtered(iteration):
            return FilterConfig()
        if not config.own_perception:
            return config.filter
        if config.filter.uncertainty == "robust":
            conformal_of(
                self.layout, iteration, CONFORMAL_ALPHA, config.collection.mc_samples, config.seed
            )
        return replace(
            config.filter,
            state_source=f"learned:{self.layout.checkpoint(iteration)}",
            samples=config.collection.mc_samples,
            spread_scale=(
                spread_scale_of(self.layout, iteration, config.collection.mc_samples, config.seed)
                if config.calibrates_spread
                else None
            ),
        )

    def _drive(self, iteration: int) -> None:
        config = self.config
        collection = CollectionConfig(
            agent="expert" if iteration == 0 else f"learned:{self.layout.checkpoint(iteration)}",
            task=config.task,
            track=config.track,
            opponents=config.opponents,
            seeds=episode_seeds(config.seed, iteration, config.episodes),
            episode=config.collection,
            safety=self.iteration_filter(iteration),
            beta=0.0 if iteration == 0 else config.beta(iteration),
            perturbation=Perturbation(config.expert_perturb if iteration == 0 else 0.0),
        )
        collected = collect_round(
            self.layout.data_dir,
            collection,
            progress=self.progress,
            workers=self.workers,
            ray_address=self.ray_address,
            num_envs=self.num_envs,
        )
        if collected.path != self.layout.round(iteration):
            raise SafeRaceError(
                f"{self.layout.data_dir} holds rounds that belong to no iteration of this run "
                f"(wrote {collected.path.name} for iteration {iteration})"
            )

    def _append_metrics(self, iteration: int, timings: dict[str, float | None]) -> None:
        manifest = json.loads(self.layout.manifest(iteration).read_text())
        episode = manifest["config"]["episodes"][0]
        held_out = episode.get("held_out", {})
        row = {
            "iteration": iteration,
            "driver": "expert" if iteration == 0 else "learned",
            "filtered": self.config.filtered(iteration),
            "completed": episode["laps_completed"] >= self.config.collection.laps,
            "lap_time_s": episode["mean_lap_time_s"],
            "duration_s": episode["duration_s"],
            "mean_abs_deviation_m": episode["mean_abs_deviation_m"],
            "max_abs_deviation_m": episode["max_abs_deviation_m"],
            "time_outside_lane_s": episode["time_outside_lane_s"],
            "longest_stop_s": episode.get("longest_stop_s"),
            "longest_standstill_s": episode.get("longest_standstill_s"),
            "intervention_rate": episode.get("intervention_rate"),
            "alarm_rate": episode.get("alarm_rate"),
            "coverage": episode.get("coverage"),
            "at_fault_collisions": episode.get("at_fault_collisions"),
            "overtakes": episode.get("overtakes"),
            "spread_scale_e_y": self._spread_scale_e_y(iteration),
            "held_out_mean_abs_deviation_m": held_out.get("mean_abs_deviation_m"),
            "held_out_time_outside_lane_s": held_out.get("time_outside_lane_s"),
            "frames": manifest["frame_count"],
            **timings,
            "trajectory": episode["trajectory"],
        }
        with open(self.layout.metrics_jsonl, "a") as handle:
            handle.write(json.dumps(row) + "\n")
        self._write_metrics_csv()

    def _write_metrics_csv(self) -> None:
        with open(self.layout.metrics_csv, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=METRIC_COLUMNS, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(self.metrics())

    def _spread_scale_e_y(self, iteration: int) -> float | None:
        """The factor on ``e_y``'s spread that ``iteration``'s drive used, if any."""
        if not (self.config.calibrates_spread and self.config.filtered(iteration)):
            return None
        record = json.loads(self.layout.spread_scale(iteration).read_text())
        return record["spread_scale"][0]

    # ------------------------------------------------------------------ folder
    def _claim_folder(self) -> None:
        """Write ``run.json``, or check that the one there describes this run."""
        path = self.layout.run_file
        wanted = self.config.fingerprint
        stored = self.layout.stored_fingerprint()
        if stored is not None:
            # as read back from JSON: tuples are lists
            wanted = json.loads(json.dumps(wanted))
            if stored != wanted:
                differing = _differing(stored, wanted)
                raise SafeRaceError(
                    f"{self.out_dir} holds a DAgger run with other settings (differing: "
                    f"{', '.join(differing)}): start it again with those, or use another --out"
                )
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        record = {"fingerprint": wanted, "saferace_version": __version__}
        path.write_text(json.dumps(record, indent=2) + "\n")

    def _link_shared_iterations(self) -> None:
        """Share iterations ``0..filter_from`` (rounds, and the checkpoints trained on them)
        with the unfiltered run this one forks from: hard links where the file system
        allows them (no second copy on disk), copies elsewhere. A source run made with
        other settings is refused."""
        source = self.fork_of
        assert source is not None
        unfiltered = replace(self.config, filter=replace(self.config.filter, kind="none"))
        DaggerRun(source.root, unfiltered, progress=False)  # checks the source's settings
        shared = self.config.filter_from
        for iteration in range(shared + 1):
            if not source.manifest(iteration).exists():
                raise SafeRaceError(
                    f"the unfiltered run in {source.root} has not reached iteration {shared} "
                    "yet: run it first"
                )
        self.layout.data_dir.mkdir(parents=True, exist_ok=True)
        self.layout.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        for iteration in range(shared + 2):
            if iteration <= shared and not self.layout.round(iteration).exists():
                shutil.copytree(
                    source.round(iteration), self.layout.round(iteration), copy_function=_link
                )
            checkpoint = source.checkpoint(iteration)
            if (
                iteration > 0
                and checkpoint.exists()
                and not self.layout.checkpoint(iteration).exists()
            ):
                _link(checkpoint, self.layout.checkpoint(iteration))
        done = {row["iteration"] for row in self.metrics()}
        with open(source.metrics_jsonl) as handle:
            rows = [json.loads(line) for line in handle if line.strip()]
        for row in rows:
            if row["iteration"] <= shared and row["iteration"] not in done:
                with open(self.layout.metrics_jsonl, "a") as handle:
                    handle.write(json.dumps(row) + "\n")


def iteration_words(row: dict) -> str:
    """An iteration's key numbers, as its progress line says them."""
    words = f"{row['driver']} driver{', filtered' if row['filtered'] else ''}, "
    words += "lap completed" if row["completed"] else "no lap completed"
    words += f", {row['time_outside_lane_s']:.2f} s outside"
    if row.get("intervention_rate") is not None:
        words += f", {100.0 * row['intervention_rate']:.0f}% of steps corrected"
    return words


def _differing(stored: dict, wanted: dict, prefix: str = "") -> list[str]:
    """The dotted names of the settings that differ between two fingerprints."""
    names = []
    for key in sorted({*stored, *wanted}):
        old, new = stored.get(key), wanted.get(key)
        if isinstance(old, dict) and isinstance(new, dict):
            names += _differing(old, new, f"{prefix}{key}.")
        elif old != new:
            names.append(prefix + key)
    return names


def _link(source: str | Path, destination: str | Path) -> None:
    """A hard link of ``source`` at ``destination`` (a copy across file systems)."""
    try:
        os.link(source, destination)
    except OSError:
        shutil.copy2(source, destination)


def episode_seed(seed: int, iteration: int, episode: int = 0) -> int:
    """The seed of one drive of an iteration (its dropout masks and look)."""
    entropy = [seed, iteration] if episode == 0 else [seed, iteration, episode]
    return int(np.random.SeedSequence(entropy).generate_state(1)[0] % 2**31)


def episode_seeds(seed: int, iteration: int, episodes: int) -> tuple[int, ...]:
    """The seeds of an iteration's ``episodes`` drives."""
    return tuple(episode_seed(seed, iteration, episode) for episode in range(episodes))
