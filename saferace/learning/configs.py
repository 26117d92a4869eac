"""The learned driver's configs: training, collection and DAgger runs.

Import-light (no torch, no MuJoCo), so that the command line builds its options from them
fast; the modules that run them import them from here.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from saferace.config import COUNT, IMAGE_SIZE, NON_NEGATIVE, POSITIVE, Bounds, check_bounds, setting
from saferace.errors import ConfigError
from saferace.eval.filter_config import FilterConfig
from saferace.learning.train_config import NETWORKS, TrainConfig
from saferace.names import (
    AUTO,
    DEFAULT_EXPERT_MODEL,
    DRIVING_TASKS,
    GENERIC_SOURCE,
    MC_SAMPLES,
    OPPONENTS_HELP,
    RANDOMIZATION_PRESETS,
    SHIFT_LOOKS,
    VEHICLE_MODELS,
)


@dataclass(frozen=True)
class Perturbation:
    """Steering noise added to the driver's action: an Ornstein-Uhlenbeck process.

    ``steer_std_rad`` is its stationary standard deviation, ``correlation_time_s`` how long
    a push lasts: correlated noise moves the car off its line far enough to need a
    recovery, where white noise at the control rate would average out.
    """

    steer_std_rad: float = setting(
        0.0,
        "DART-style steering noise on the driver, its standard deviation (rad); the label "
        "stays the expert's",
        flag="--perturb",
        metavar="STEER_STD_RAD",
        bounds=NON_NEGATIVE,
    )
    correlation_time_s: float = setting(
        0.5,
        "how long a push of the steering noise lasts (its correlation time)",
        flag="--perturb-correlation-s",
        bounds=POSITIVE,
    )

    def __post_init__(self) -> None:
        check_bounds(self)


@dataclass(frozen=True)
class EpisodeSettings:
    """How every episode of a collection is driven and recorded: laps, time, camera, the
    labelling expert, the look, and the part of the lap kept for training."""

    laps: int = setting(3, "laps per episode", bounds=COUNT)
    max_seconds: float | None = setting(
        None, "end an episode after this much simulated time", bounds=POSITIVE
    )
    image_size: int = setting(64, "onboard image height and width (pixels)", bounds=IMAGE_SIZE)
    stereo: bool = setting(False, "stereo camera pair (6 channels)")
    expert_model: str = setting(
        DEFAULT_EXPERT_MODEL,
        "vehicle model of the labelling expert MPC (and of an expert driver)",
        flag="--model",
        choices=VEHICLE_MODELS,
    )
    mc_samples: int = setting(
        MC_SAMPLES, "MC-dropout samples per step of a learned driver", bounds=COUNT
    )
    train_fraction: float = setting(
        1.0,
        "keep frames on this first part of the lap; the rest is held out, never trained on",
        bounds=Bounds(above=0, maximum=1),
    )
    randomize: str = setting(
        "none",
        "visual domain randomisation: a look per episode seed (a preset, or a shift "
        "severity's looks)",
        choices=RANDOMIZATION_PRESETS + SHIFT_LOOKS,
        metavar="PRESET",
    )

    def __post_init__(self) -> None:
        check_bounds(self)


@dataclass(frozen=True)
class CollectionConfig:
    """What one round records: driver, task, track, an episode per seed, the opponents
    (none: the task's own), how each is driven (``episode``), the steering noise, the
    filter and the expert's share."""

    agent: str = setting(
        "expert",
        "expert, pure-pursuit, drift, weave, speeding, learned:CHECKPOINT or MODULE:FACTORY",
    )
    task: str = setting(
        "RacingLine", "the reference line to follow (Overtake: in traffic)", choices=DRIVING_TASKS
    )
    track: str = setting("technical", "built-in track name or track CSV path")
    seeds: tuple[int, ...] = setting((0,), "one episode per seed", bounds=NON_NEGATIVE)
    opponents: tuple[str, ...] = setting(
        (), OPPONENTS_HELP + "; the expert labels passing or following them", metavar="SPEC"
    )
    episode: EpisodeSettings = field(default_factory=EpisodeSettings)
    perturbation: Perturbation = field(default_factory=Perturbation)
    safety: FilterConfig = field(default_factory=FilterConfig)
    beta: float = 0.0

    def __post_init__(self) -> None:
        check_bounds(self)
        if not 0.0 <= self.beta <= 1.0:
            raise ConfigError("beta", f"must be in [0, 1], got {self.beta}")
        if not self.seeds:
            raise ConfigError("seeds", "must name at least one episode")

    def as_dict(self) -> dict:
        """Flat, as a round's manifest keeps it (the episode settings beside the rest)."""
        values = asdict(self)
        values.update(values.pop("episode"))
        values["image_size"] = [self.episode.image_size] * 2
        values["safety"] = self.safety.as_dict()
        return values


def _dagger_training() -> TrainConfig:
    return TrainConfig(epochs=9, val_stretch=None, state_uncertainty=AUTO)


def _dagger_collection() -> EpisodeSettings:
    return EpisodeSettings(laps=1, max_seconds=60.0, train_fraction=0.7)


@dataclass(frozen=True)
class DaggerConfig:
    """One DAgger run: what the iterations share, with three nested configs.

    ``training`` trains each iteration (its ``seed`` seeds the run: training, dropout masks
    and looks; the run sets ``init`` and ``networks``); ``collection`` drives each iteration
    (``laps`` per drive, the first counts for the tables; ``train_fraction`` of the lap kept
    for training); ``filter`` is the filter of the iterations after ``filter_from`` (the
    paper's k): its ``state_source`` is ``generic[:RECIPE]`` (the default: the generic
    perception model), ``learned`` (the paper's: the run fills in each iteration's
    checkpoint and ``collection.mc_samples``) or None (the truth).
    """

    task: str = setting(
        "CenterLine", "the reference line (Overtake: in traffic)", choices=DRIVING_TASKS
    )
    track: str = setting("lab", "built-in track name or track CSV path")
    opponents: tuple[str, ...] = setting(
        (), OPPONENTS_HELP + "; the expert labels passing or following them", metavar="SPEC"
    )
    iterations: int = setting(10, "iterations after the expert's", bounds=NON_NEGATIVE)
    filter_from: int = setting(
        2,
        "the iterations after K drive through the filter (the paper's k)",
        metavar="K",
        bounds=NON_NEGATIVE,
    )
    warm_start: bool = setting(
        True,
        "retrain each iteration from random weights instead of fine-tuning the last ones",
        flag="--from-scratch",
    )
    expert_perturb: float = setting(
        0.0,
        "steering noise on the expert's iteration 0 (the paper's expert drove clean)",
        metavar="STEER_STD_RAD",
        bounds=NON_NEGATIVE,
    )
    beta_rampdown: int = setting(
        0,
        "the expert acts on a share 1 - i/R of iteration i's steps (0: never, as the paper)",
        metavar="R",
        bounds=NON_NEGATIVE,
    )
    calibrate_spread: bool = setting(
        False,
        "widen the state network's MC-dropout spread by the factor that matches it to its "
        "error on the previous round, which it never saw",
    )
    episodes: int = setting(1, "drives per iteration (the first is reported)", bounds=COUNT)
    training: TrainConfig = field(default_factory=_dagger_training)
    collection: EpisodeSettings = field(default_factory=_dagger_collection)
    filter: FilterConfig = field(default_factory=lambda: FilterConfig(state_source=GENERIC_SOURCE))

    def __post_init__(self) -> None:
        check_bounds(self)
        if self.training.state_uncertainty == AUTO:
            honest = self.own_perception and self.filter.uncertainty == "robust"
            method = "ensemble" if honest else "mc-dropout"
            object.__setattr__(self, "training", replace(self.training, state_uncertainty=method))
        if self.task not in DRIVING_TASKS:
            raise ConfigError(
                "task", f"must be one of {', '.join(DRIVING_TASKS)}, got {self.task!r}"
            )
        if self.training.val_stretch is not None:
            raise ConfigError(
                "val_stretch",
                "must be None: a DAgger run scores the held-out part of the lap by driving it: set "
                "train_fraction instead",
            )
        if self.training.init is not None or self.training.networks != NETWORKS:
            raise ConfigError(
                "init", "must be None: a DAgger run warm-starts each iteration itself"
            )
        source = self.filter.state_source
        if source not in (None, "learned") and source.partition(":")[0] != GENERIC_SOURCE:
            raise ConfigError(
                "state_source",
                f"must be generic[:RECIPE] (the generic perception model), learned (the run's "
                f"own networks) or None (the truth), got {source!r}",
            )
        if (
            self.own_perception
            and self.filter.uncertainty == "robust"
            and self.collection.train_fraction >= 1.0
        ):
            raise ConfigError(
                "uncertainty",
                "robust calibrates the state network on the part of the lap no network "
                "trained on: it needs train_fraction < 1",
            )
        if self.calibrate_spread and self.perceived and not self.own_perception:
            message = "widens the run's own state network's spread: add --state-source learned"
            raise ConfigError("calibrate_spread", message)
        if self.calibrates_spread and self.filter.uncertainty == "robust":
            raise ConfigError(
                "calibrate_spread",
                "widens the spread of the chance constraints; the robust mode holds the car "
                "over the conformal interval, which the widened samples would hide: ask for "
                "the chance constraints (--filter-uncertainty chance) or drop it",
            )
        if self.calibrates_spread and self.collection.train_fraction >= 1.0:
            raise ConfigError(
                "calibrate_spread",
                "fits on the part of the lap no network trained on: it needs train_fraction < 1",
            )

    @property
    def seed(self) -> int:
        return self.training.seed

    @property
    def filters(self) -> bool:
        return self.filter.kind != "none"

    @property
    def perceived(self) -> bool:
        """Whether the filtered drives see a state network's samples (not the truth)."""
        return self.filters and self.filter.state_source is not None

    @property
    def own_perception(self) -> bool:
        """Whether the filtered drives see the run's own state network (the paper's)."""
        return self.filters and self.filter.state_source == "learned"

    @property
    def calibrates_spread(self) -> bool:
        """Whether the filtered drives widen the run's state network's spread."""
        return self.calibrate_spread and self.own_perception

    @property
    def trained_networks(self) -> tuple[str, ...]:
        """The networks each warm-started iteration trains: a fork fed the truth or the
        generic perception model drives and filters without its own state network, so it
        keeps the one it forked with."""
        if self.filters and not self.own_perception and self.warm_start:
            return ("control",)
        return NETWORKS

    @property
    def fingerprint(self) -> dict:
        """What makes two runs the same run: the iterations may be extended, and an
        unfiltered run is the same whatever filter its forks will use.

        Flat, with the names run.json has always used, and JSON's types (lists, not
        tuples), so that a folder written before the configs were nested, or read back
        from its run.json, is the same run; a setting at its default that an older run
        could not have had is left out."""
        training, collection, safety = self.training, self.collection, self.filter
        values: dict[str, Any] = {
            "task": self.task,
            "track": self.track,
            "opponents": list(self.opponents),
            "filter": safety.kind,
            "filter_from": self.filter_from,
            "state_source": "oracle" if safety.state_source is None else safety.state_source,
            "epochs": training.epochs,
            "min_train_steps": training.min_steps,
            "max_train_steps": training.max_steps,
            "batch_size": training.batch_size,
            "learning_rate": training.learning_rate,
            "warm_start": self.warm_start,
            "stereo": collection.stereo,
            "image_size": collection.image_size,
            "train_fraction": collection.train_fraction,
            "laps": collection.laps,
            "expert_perturb": self.expert_perturb,
            "seed": training.seed,
            "expert_model": collection.expert_model,
            "filter_model": safety.model,
            "filter_gains": safety.gains,
            "map_curvature": safety.map_curvature,
            "calibrate_spread": self.calibrate_spread,
            "fuse_odometry": safety.fuse_odometry and self.perceived,
            "mc_samples": collection.mc_samples,
            "beta_rampdown": self.beta_rampdown,
            "max_seconds": collection.max_seconds,
            "randomize": collection.randomize,
            "episodes": self.episodes,
            "trained_networks": list(self.trained_networks),
        }
        newer: dict[str, tuple[Any, Any]] = {  # settings the flat config never had
            "dropout": (training.dropout, 0.2),
            "backbone_weights": (training.backbone_weights, None),
            "state_noise": (safety.state_noise, None),
            "filter_samples": (safety.samples, FilterConfig.samples),
            "probabilistic": (safety.probabilistic, True),
            "eta": (safety.eta, 0.95),
            "spread_scale": (safety.spread_scale, None),
            "uncertainty": (safety.uncertainty, "chance"),
            "adaptive": (safety.adaptive, None),
            "state_uncertainty": (training.state_uncertainty, "mc-dropout"),
            "ensemble_members": (
                training.ensemble_members if training.state_uncertainty != "mc-dropout" else 5,
                5,
            ),
            "packed_alpha": (training.packed_alpha, 2.0),
            "packed_gamma": (training.packed_gamma, 1),
            "augment": (training.augment, False),
            "patience": (training.patience, 0),
            "opponent_noise_m": (safety.opponent_noise_m, 0.0),
        }
        for name, (value, default) in newer.items():
            if value != default:
                values[name] = value
        defaults: tuple[tuple[str, Any], ...] = (
            ("opponents", []),
            ("randomize", "none"),
            ("episodes", 1),
            ("fuse_odometry", False),
            ("max_train_steps", 0),
            ("trained_networks", list(NETWORKS)),
        )
        for name, default in defaults:
            if values.get(name) == default:  # the same run as one made before the option
                del values[name]
        if not self.filters:
            for name in (
                "filter_from", "state_source", "filter_model", "filter_gains", "map_curvature",
                "calibrate_spread", "fuse_odometry", "state_noise", "filter_samples",
                "probabilistic", "eta", "spread_scale", "uncertainty", "adaptive",
                "opponent_noise_m",
            ):  # fmt: skip
                values.pop(name, None)
        return json.loads(json.dumps(values))

    def filtered(self, iteration: int) -> bool:
        return self.filters and iteration > self.filter_from

    def beta(self, iteration: int) -> float:
        """Share of steps the expert drives in ``iteration``: 1 at iteration 0, then the
        linear ramp ``1 - i / beta_rampdown`` (none without a ramp, as in the paper)."""
        if iteration == 0:
            return 1.0
        if not self.beta_rampdown:
            return 0.0
        return max(0.0, 1.0 - iteration / self.beta_rampdown)
