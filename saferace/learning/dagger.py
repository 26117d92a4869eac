"""DAgger with and without the safety filter (paper Sec. 2.3 and 4, "Training cycle").

Iteration 0: the expert MPC drives one lap from ground truth and the frames are recorded.
Iteration ``i >= 1``: both networks are trained on the rounds of iterations ``0..i-1``
(fine-tuned from iteration ``i-1``'s weights, as the authors did, or from scratch), then the
control network drives from the camera and the velocities while the expert labels every
frame; the round joins the aggregate. A drive ends when the lap is done or the car has left
the lane (the task terminates it). With ``filter="cbf"`` the iterations after
``filter_from`` drive through :class:`~saferace.safety.filter.SafetyFilter` fed the state
network's MC-dropout samples (the perceived state; ``state_source="oracle"`` feeds it the
truth instead). A filtered run forks from the unfiltered one: it shares iterations
``0..filter_from`` with it, bit for bit (copied with ``fork_of``, or recomputed: every
stage is seeded and deterministic). With ``train_fraction < 1`` frames are kept only on
that first part of the lap, and each iteration is also scored on the rest of it.

A run lives in one folder::

    run.json                      the settings (a run with other settings is refused)
    data/round_NNNN/              iteration N's round (saferace.learning.rounds), its frames
                                  past the train fraction apart in held_out.npz
    checkpoints/iteration_NN.pt   the networks that drove iteration N
    checkpoints/iteration_NN.spread_scale.json
                                  their state network's calibration (calibrate_spread)
    metrics.jsonl, metrics.csv    one row per iteration, written as soon as it exists

Every round and checkpoint is written atomically and training keeps its progress per epoch,
so a killed run started again with the same settings continues where it stopped.
"""

from __future__ import annotations

import csv
import json
import re
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

import saferace
from saferace.errors import SafeRaceError
from saferace.eval.filters import FilterConfig
from saferace.learning.calibration import inside_lane, spread_scale
from saferace.learning.checkpoint import load_checkpoint, save_checkpoint, write_text_atomically
from saferace.learning.collect import CollectionConfig, Perturbation, collect_round
from saferace.learning.rounds import HELD_OUT_FILE, load_rounds
from saferace.learning.training import NETWORKS, TrainConfig, train_networks
from saferace.track import Track

RUN_FILE = "run.json"
CHECKPOINT_NAME = re.compile(r"^iteration_\d+\.pt$")
METRICS_FILE = "metrics.jsonl"
#: Held-out frames a state network's spread is calibrated on, at least.
MIN_CALIBRATION_FRAMES = 20
STATE_SOURCES = ("learned", "oracle")
#: Settings that only a filtered run uses.
FILTER_SETTINGS = (
    "filter_from",
    "state_source",
    "filter_model",
    "filter_gains",
    "map_curvature",
    "calibrate_spread",
    "fuse_odometry",
)
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
    "intervention_rate",
    "spread_scale_e_y",
    "held_out_mean_abs_deviation_m",
    "held_out_time_outside_lane_s",
    "frames",
    "train_seconds",
    "collect_seconds",
)


@dataclass(frozen=True)
class DaggerConfig:
    """One DAgger run. ``filter_from`` is the paper's k: iterations after it are filtered.

    ``laps`` per drive (the first counts for the tables); ``expert_perturb``: steering noise
    (rad) on the expert's iteration 0, so that its frames show the car off its line (the
    paper's expert drove clean); ``map_curvature``: the filter takes the curvature from the
    map rather than from the state network (see :class:`~saferace.safety.filter.SafetyFilter`);
    ``fuse_odometry``: the filter fuses the state network's samples with odometry
    (:class:`~saferace.safety.state_fusion.OdometryFusedStateSource`);
    ``min_train_steps``/``max_train_steps`` (0: none): bounds on each training's gradient
    steps (see :class:`~saferace.learning.training.TrainConfig`).
    """

    task: str = "CenterLine"
    track: str = "lab"
    iterations: int = 10
    filter: str = "none"
    filter_from: int = 2
    state_source: str = "learned"
    epochs: int = 9
    min_train_steps: int = 0
    max_train_steps: int = 0
    batch_size: int = 32
    learning_rate: float = 1e-3
    warm_start: bool = True
    stereo: bool = False
    image_size: int = 64
    train_fraction: float = 0.7
    laps: int = 1
    expert_perturb: float = 0.0
    seed: int = 0
    expert_model: str = "dynamic"
    filter_model: str = "kinematic"
    filter_gains: str = "paper"
    map_curvature: bool = False
    calibrate_spread: bool = False
    fuse_odometry: bool = False
    mc_samples: int = 10
    beta_rampdown: int = 0
    max_seconds: float = 60.0
    randomize: str = "none"
    episodes: int = 1

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise SafeRaceError(f"episodes must be at least 1, got {self.episodes}")
        if self.filter not in ("none", "cbf"):
            raise SafeRaceError(f"filter must be none or cbf, got {self.filter!r}")
        if self.state_source not in STATE_SOURCES:
            raise SafeRaceError(
                f"state_source must be learned or oracle, got {self.state_source!r}"
            )
        if self.iterations < 0 or self.filter_from < 0 or self.beta_rampdown < 0:
            raise SafeRaceError("iterations, filter_from and beta_rampdown must not be negative")
        if self.max_seconds <= 0:
            raise SafeRaceError(f"max_seconds must be positive, got {self.max_seconds}")
        if self.min_train_steps < 0 or self.max_train_steps < 0:
            raise SafeRaceError("min_train_steps and max_train_steps must not be negative")
        if self.max_train_steps and self.min_train_steps > self.max_train_steps:
            raise SafeRaceError(
                f"min_train_steps {self.min_train_steps} is above max_train_steps "
                f"{self.max_train_steps}"
            )
        if self.calibrates_spread and self.train_fraction >= 1.0:
            raise SafeRaceError(
                "calibrate_spread fits on the part of the lap no network trained on: it needs "
                "train_fraction < 1"
            )

    @property
    def calibrates_spread(self) -> bool:
        """Whether the filtered drives widen the state network's spread (``calibrate_spread``
        does nothing to the oracle state)."""
        return self.calibrate_spread and self.filter == "cbf" and self.state_source == "learned"

    @property
    def fuses_odometry(self) -> bool:
        """Whether the filtered drives fuse the state network with odometry
        (``fuse_odometry`` does nothing to the oracle state)."""
        return self.fuse_odometry and self.filter == "cbf" and self.state_source == "learned"

    @property
    def trained_networks(self) -> tuple[str, ...]:
        """The networks each warm-started iteration trains: the true-state fork drives and
        filters without its state network, so it keeps the one it forked with."""
        if self.filter == "cbf" and self.state_source == "oracle" and self.warm_start:
            return ("control",)
        return NETWORKS

    @property
    def fingerprint(self) -> dict:
        """What makes two runs the same run: the iterations may be extended, and an
        unfiltered run is the same whatever filter its forks will use."""
        values = asdict(self)
        del values["iterations"]
        values["fuse_odometry"] = self.fuses_odometry
        values["trained_networks"] = list(self.trained_networks)
        for name, default in (
            ("randomize", "none"),
            ("episodes", 1),
            ("fuse_odometry", False),
            ("max_train_steps", 0),
            ("trained_networks", list(NETWORKS)),
        ):
            if values.get(name) == default:  # the same run as one made before the option existed
                del values[name]
        if self.filter == "none":
            for name in FILTER_SETTINGS:
                values.pop(name, None)
        return values

    def filtered(self, iteration: int) -> bool:
        return self.filter == "cbf" and iteration > self.filter_from

    def beta(self, iteration: int) -> float:
        """Share of steps the expert drives in ``iteration``: 1 at iteration 0, then the
        linear ramp ``1 - i / beta_rampdown`` (none without a ramp, as in the paper)."""
        if iteration == 0:
            return 1.0
        if not self.beta_rampdown:
            return 0.0
        return max(0.0, 1.0 - iteration / self.beta_rampdown)


class DaggerRun:
    """A DAgger run in its folder: :meth:`run` does what is missing, iteration by iteration."""

    def __init__(
        self,
        out_dir: str | Path,
        config: DaggerConfig,
        fork_of: str | Path | None = None,
        progress: bool = True,
        label: str = "dagger",
        workers: int = 1,
        ray_address: str | None = None,
    ) -> None:
        """``workers``/``ray_address``: where an iteration's episodes are driven (see
        :func:`~saferace.learning.collect.collect_round`); the rounds are the same."""
        self.workers, self.ray_address = workers, ray_address
        self.out_dir = Path(out_dir)
        self.config = config
        self.fork_of = None if fork_of is None else Path(fork_of)
        self.progress = progress
        self.label = label
        self.data_dir = self.out_dir / "data"
        self.checkpoint_dir = self.out_dir / "checkpoints"
        self._claim_folder()

    # ------------------------------------------------------------------ layout
    def checkpoint_path(self, iteration: int) -> Path:
        return self.checkpoint_dir / f"iteration_{iteration:02d}.pt"

    def round_path(self, iteration: int) -> Path:
        return self.data_dir / f"round_{iteration:04d}"

    def metrics(self) -> list[dict]:
        """The iterations' metric rows written so far."""
        path = self.out_dir / METRICS_FILE
        if not path.exists():
            return []
        with open(path) as handle:
            return [json.loads(line) for line in handle if line.strip()]

    # ------------------------------------------------------------------ stages
    def run(self) -> list[dict]:
        """Every missing stage of iterations ``0..iterations``; all metric rows."""
        if self.fork_of is not None:
            self._copy_shared_iterations()
        done = {row["iteration"] for row in self.metrics()}
        bar = tqdm(
            total=self.config.iterations + 1,
            initial=len(done),
            desc=self.label,
            unit="iteration",
            disable=None if self.progress else True,
        )
        with bar:
            for iteration in range(self.config.iterations + 1):
                if iteration in done:
                    continue
                timings = {}
                if iteration > 0 and not self.checkpoint_path(iteration).exists():
                    bar.set_postfix_str(f"iteration {iteration}: training")
                    timings["train_seconds"] = self._train(iteration)
                if not (self.round_path(iteration) / "manifest.json").exists():
                    bar.set_postfix_str(f"iteration {iteration}: driving")
                    timings["collect_seconds"] = self._collect(iteration)
                self._append_metrics(iteration, timings)
                bar.update()
        return self.metrics()

    def _train(self, iteration: int) -> float:
        """Train the networks of ``iteration`` on rounds ``0..iteration-1``; seconds taken."""
        started = time.perf_counter()
        config = self.config
        rounds = [self.round_path(i) for i in range(iteration)]
        init = self.checkpoint_path(iteration - 1) if config.warm_start and iteration > 1 else None
        training = TrainConfig(
            epochs=config.epochs,
            min_steps=config.min_train_steps,
            max_steps=config.max_train_steps,
            networks=NETWORKS if init is None else config.trained_networks,
            batch_size=config.batch_size,
            learning_rate=config.learning_rate,
            seed=config.seed,
            val_stretch=None,  # the held-out part of the lap is scored by driving it
            init=None if init is None else str(init),
        )
        path = self.checkpoint_path(iteration)
        resume_file = path.with_suffix(".resume.pt")
        control, state, metadata = train_networks(
            load_rounds(rounds), training, self.progress, resume_file
        )
        metadata["dagger_iteration"] = iteration
        save_checkpoint(path, control, state, metadata)
        resume_file.unlink(missing_ok=True)
        return time.perf_counter() - started

    def _collect(self, iteration: int) -> float:
        """Drive iteration ``iteration`` and write its round; seconds taken."""
        started = time.perf_counter()
        config = self.config
        checkpoint = self.checkpoint_path(iteration)
        safety = FilterConfig()
        if config.filtered(iteration):
            learned = config.state_source == "learned"
            safety = FilterConfig(
                kind="cbf",
                model=config.filter_model,
                gains=config.filter_gains,
                samples=config.mc_samples,
                state_source=f"learned:{checkpoint}" if learned else None,
                map_curvature=config.map_curvature,
                fuse_odometry=config.fuses_odometry,
                spread_scale=(
                    spread_scale_of(self.out_dir, iteration, config.mc_samples, config.seed)
                    if config.calibrates_spread
                    else None
                ),
            )
        collection = CollectionConfig(
            agent="expert" if iteration == 0 else f"learned:{checkpoint}",
            task=config.task,
            track=config.track,
            seeds=episode_seeds(config.seed, iteration, config.episodes),
            laps=config.laps,
            max_seconds=config.max_seconds,
            safety=safety,
            expert_model=config.expert_model,
            image_size=(config.image_size, config.image_size),
            stereo=config.stereo,
            mc_samples=config.mc_samples,
            train_fraction=config.train_fraction,
            beta=0.0 if iteration == 0 else config.beta(iteration),
            perturbation=Perturbation(config.expert_perturb if iteration == 0 else 0.0),
            randomize=config.randomize,
        )
        collected = collect_round(
            self.data_dir,
            collection,
            progress=self.progress,
            workers=self.workers,
            ray_address=self.ray_address,
        )
        if collected.path.name != self.round_path(iteration).name:
            raise SafeRaceError(
                f"{self.data_dir} holds rounds that belong to no iteration of this run "
                f"(wrote {collected.path.name} for iteration {iteration})"
            )
        return time.perf_counter() - started

    def _append_metrics(self, iteration: int, timings: dict[str, float]) -> None:
        manifest = json.loads((self.round_path(iteration) / "manifest.json").read_text())
        episode = manifest["config"]["episodes"][0]
        held_out = episode.get("held_out", {})
        row = {
            "iteration": iteration,
            "driver": "expert" if iteration == 0 else "learned",
            "filtered": self.config.filtered(iteration),
            "completed": episode["laps_completed"] >= self.config.laps,
            "lap_time_s": episode["mean_lap_time_s"],
            "duration_s": episode["duration_s"],
            "mean_abs_deviation_m": episode["mean_abs_deviation_m"],
            "max_abs_deviation_m": episode["max_abs_deviation_m"],
            "time_outside_lane_s": episode["time_outside_lane_s"],
            "intervention_rate": episode.get("intervention_rate"),
            "spread_scale_e_y": self._spread_scale_e_y(iteration),
            "held_out_mean_abs_deviation_m": held_out.get("mean_abs_deviation_m"),
            "held_out_time_outside_lane_s": held_out.get("time_outside_lane_s"),
            "frames": manifest["frame_count"],
            "train_seconds": timings.get("train_seconds"),
            "collect_seconds": timings.get("collect_seconds"),
            "trajectory": episode["trajectory"],
        }
        with open(self.out_dir / METRICS_FILE, "a") as handle:
            handle.write(json.dumps(row) + "\n")
        rows = self.metrics()
        with open(self.out_dir / "metrics.csv", "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=METRIC_COLUMNS, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)

    def _spread_scale_e_y(self, iteration: int) -> float | None:
        """The factor on ``e_y``'s spread that ``iteration``'s drive used, if any."""
        if not (self.config.calibrates_spread and self.config.filtered(iteration)):
            return None
        return json.loads(spread_scale_path(self.out_dir, iteration).read_text())["spread_scale"][0]

    # ------------------------------------------------------------------ folder
    def _claim_folder(self) -> None:
        """Write ``run.json``, or check that the one there describes this run."""
        path = self.out_dir / RUN_FILE
        wanted = {"fingerprint": self.config.fingerprint}
        if path.exists():
            stored = json.loads(path.read_text())
            if stored["fingerprint"] != wanted["fingerprint"]:
                differing = sorted(
                    key
                    for key in {*wanted["fingerprint"], *stored["fingerprint"]}
                    if stored["fingerprint"].get(key) != wanted["fingerprint"].get(key)
                )
                raise SafeRaceError(
                    f"{self.out_dir} holds a DAgger run with other settings (differing: "
                    f"{', '.join(differing)}): start it again with those, or use another --out"
                )
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        path.write_text(
            json.dumps({**wanted, "saferace_version": saferace.__version__}, indent=2) + "\n"
        )

    def _copy_shared_iterations(self) -> None:
        """Copy iterations ``0..filter_from`` (rounds, and the checkpoints trained on them)
        from the unfiltered run this one forks from."""
        source = DaggerRun(self.fork_of, replace(self.config, filter="none"), progress=False)
        shared = self.config.filter_from
        for iteration in range(shared + 1):
            if not (source.round_path(iteration) / "manifest.json").exists():
                raise SafeRaceError(
                    f"the unfiltered run in {self.fork_of} has not reached iteration {shared} "
                    "yet: run it first"
                )
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        for iteration in range(shared + 2):
            if iteration <= shared and not self.round_path(iteration).exists():
                shutil.copytree(source.round_path(iteration), self.round_path(iteration))
            checkpoint = source.checkpoint_path(iteration)
            if (
                iteration > 0
                and checkpoint.exists()
                and not self.checkpoint_path(iteration).exists()
            ):
                shutil.copy2(checkpoint, self.checkpoint_path(iteration))
        done = {row["iteration"] for row in self.metrics()}
        for row in source.metrics():
            if row["iteration"] <= shared and row["iteration"] not in done:
                with open(self.out_dir / METRICS_FILE, "a") as handle:
                    handle.write(json.dumps(row) + "\n")


def spread_scale_path(run_dir: str | Path, iteration: int) -> Path:
    return Path(run_dir, "checkpoints", f"iteration_{iteration:02d}.spread_scale.json")


def spread_scale_of(
    run_dir: str | Path, iteration: int, mc_samples: int, seed: int
) -> tuple[float, float, float]:
    """The calibration of the state network of a run's ``iteration``, fitted on the held-out
    frames (the part of the lap it never trained on, with the car inside its lane) of the
    latest round that has at least :data:`MIN_CALIBRATION_FRAMES` of them; written once
    beside the checkpoint, read back afterwards."""
    path = spread_scale_path(run_dir, iteration)
    if not path.exists():
        checkpoint = Path(run_dir, "checkpoints", f"iteration_{iteration:02d}.pt")
        network = load_checkpoint(checkpoint).state
        for previous in range(iteration - 1, -1, -1):
            round_dir = Path(run_dir, "data", f"round_{previous:04d}")
            manifest = json.loads((round_dir / "manifest.json").read_text())
            if manifest.get("held_out_frame_count", 0) < MIN_CALIBRATION_FRAMES:
                continue
            frames = load_rounds([round_dir], held_out=True)
            track = Track.load(manifest["config"]["track_argument"])
            inside = inside_lane(frames, track)
            if inside.sum() >= MIN_CALIBRATION_FRAMES:
                break
        else:
            raise SafeRaceError(
                f"no round of {run_dir} holds {MIN_CALIBRATION_FRAMES} held-out frames with "
                "the car inside its lane to calibrate the state network on (is the train "
                "fraction below 1?)"
            )
        scale = spread_scale(network, frames.subset(inside), mc_samples, seed=seed)
        record = {
            "spread_scale": scale.tolist(),
            "fitted_on": f"{round_dir.name} ({HELD_OUT_FILE})",
            "frames": int(inside.sum()),
        }
        write_text_atomically(path, json.dumps(record, indent=2) + "\n")
    return tuple(json.loads(path.read_text())["spread_scale"])


def episode_seed(seed: int, iteration: int, episode: int = 0) -> int:
    """The seed of one drive of an iteration (its dropout masks and look)."""
    entropy = [seed, iteration] if episode == 0 else [seed, iteration, episode]
    return int(np.random.SeedSequence(entropy).generate_state(1)[0] % 2**31)


def episode_seeds(seed: int, iteration: int, episodes: int) -> tuple[int, ...]:
    """The seeds of an iteration's ``episodes`` drives."""
    return tuple(episode_seed(seed, iteration, episode) for episode in range(episodes))


def final_checkpoint(run_dir: str | Path) -> Path:
    """The checkpoint that drove a run's last iteration."""
    checkpoints = sorted(
        path
        for path in Path(run_dir, "checkpoints").glob("iteration_*.pt")
        if CHECKPOINT_NAME.match(path.name)
    )
    if not checkpoints:
        raise SafeRaceError(f"{run_dir} holds no trained checkpoint yet")
    return checkpoints[-1]
