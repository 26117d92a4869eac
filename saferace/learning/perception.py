"""The generic perception model: one state network for tracks and looks it never saw.

A DAgger learner's own state network after a round has seen one lap of one track, and no
calibration makes it honest off that lap. The generic model is trained once, on frames of
many procedurally generated tracks (:func:`~saferace.track.random_track.write_random_track`,
a seed each, of random size) in randomised looks, driven by the expert with steering noise
and by the reckless agents behind the oracle filter (the frames a filter meets: cars near
the lane's edge, heading out). It is one heteroscedastic ResNet-18 (mean and variance per
output), so the learned step costs one backbone. It is then calibrated on other random
tracks, track by track (:func:`~saferace.safety.uncertainty.conformal.group_calibration`): the
interval's scale and the feature monitor's threshold are the largest of the per-track
ones, so they hold on each unseen track, not only pooled over frames.

Everything lives in a cache folder per recipe (``$SAFERACE_CACHE``, default
``~/.cache/saferace``, then ``perception/RECIPE``): the tracks, the rounds, the training's
resume file, the model and a manifest (recipe, seeds, commit, packages, hashes, time per
stage). Every stage is resumable: an interrupted build continues where it stopped, and a
built model is reused. ``--state-source generic`` (or ``generic:RECIPE``) names it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from saferace.cache import cache_root
from saferace.errors import SafeRaceError
from saferace.eval.filter_config import FilterConfig
from saferace.eval.parallel import run_jobs
from saferace.eval.runner import git_revision, package_versions
from saferace.learning.agent import LearnedStateSource, check_generic_image_shape
from saferace.learning.calibration import CALIBRATED_OUTPUTS, inside_lane
from saferace.learning.checkpoint import (
    CONFORMAL_KEY,
    load_checkpoint,
    save_checkpoint,
    write_text_atomically,
)
from saferace.learning.collect import collect_round
from saferace.learning.configs import CollectionConfig, EpisodeSettings, Perturbation, TrainConfig
from saferace.learning.rounds import FrameSet, load_rounds, round_dirs
from saferace.learning.training import train_networks
from saferace.learning.training_data import network_data
from saferace.learning.validation import predict_frames
from saferace.names import (
    CONFORMAL_ALPHA,
    GENERIC_SOURCE,
    PERCEPTION_IMAGE_SIZE,
    PERCEPTION_RECIPES,
)
from saferace.progress import Progress, duration_words
from saferace.safety.uncertainty.conformal import ConformalCalibration, group_calibration
from saferace.safety.uncertainty.feature_monitor import feature_monitor
from saferace.safety.uncertainty.intervals import ConformalStateSource
from saferace.safety.uncertainty.lane_middle import LaneMiddleStateSource, lane_middle_state
from saferace.safety.uncertainty.state_sources import StateSource
from saferace.track import Track
from saferace.track.random_track import write_random_track
from saferace.version import __version__

LOG = logging.getLogger(__name__)
MODEL_FILE = "model.pt"
MANIFEST_FILE = "manifest.json"
RECIPE_FILE = "recipe.json"
#: Training frames the feature monitor's Gaussian is fitted on, at most.
MONITOR_FIT_FRAMES = 4000


@dataclass(frozen=True)
class PerceptionRecipe:
    """What a generic perception model is made of: the random tracks it trains and
    calibrates on (their seeds), their sizes, who drives, in which tasks and looks, for how
    long, the steering noise, and the training."""

    name: str
    train_track_seeds: tuple[int, ...]
    calibration_track_seeds: tuple[int, ...]
    drivers: tuple[str, ...] = ("expert", "drift", "weave", "speeding")
    tasks: tuple[str, ...] = ("CenterLine", "RacingLine")
    looks: tuple[str, ...] = ("none", "strong")
    calibration_looks: tuple[str, ...] = ("none",)
    radius_range_m: tuple[float, float] = (2.5, 40.0)
    lane_width_range_m: tuple[float, float] = (0.7, 2.5)
    seconds_per_drive: float = 20.0
    steer_noise_rad: float = 0.08
    mirror: bool = True
    lane_middle: bool = True
    lane_fraction: bool = True
    epochs: int = 6
    lr_schedule: str = "cosine"
    batch_size: int = 64
    alpha: float = CONFORMAL_ALPHA
    image_size: int = PERCEPTION_IMAGE_SIZE
    seed: int = 0

    def drives(self, part: str, track_index: int) -> list[tuple[str, str, str]]:
        """``(driver, task, look)`` of each drive on the ``track_index``-th track of its
        ``part``: every driver once, the looks (of the part) and tasks taking turns from
        track to track."""
        looks = self.looks if part == "train" else self.calibration_looks
        tasks = self.tasks
        return [
            (
                driver,
                tasks[(index // len(looks) + track_index) % len(tasks)],
                looks[(index + track_index) % len(looks)],
            )
            for index, driver in enumerate(self.drivers)
        ]


#: The recipes by name (``saferace.names.PERCEPTION_RECIPES``). Track seeds start far from
#: the small ones tests and examples use, so an evaluation on a fresh random track is one
#: nothing was trained or calibrated on.
RECIPES = {
    "default": PerceptionRecipe(
        "default",
        tuple(range(90001, 90049)),
        tuple(range(91001, 91013)),
        seconds_per_drive=4.0,
        epochs=6,
    ),
    "quick": PerceptionRecipe(
        "quick",
        (90001, 90002, 90003),
        (91001, 91002),
        drivers=("expert", "drift"),
        seconds_per_drive=8.0,
        epochs=2,
        batch_size=32,
    ),
}
assert tuple(RECIPES) == PERCEPTION_RECIPES, "one recipe per name"


def recipe_named(source: str) -> PerceptionRecipe:
    """The recipe of ``generic`` (the default) or ``generic:RECIPE``."""
    kind, _, name = source.partition(":")
    if kind != GENERIC_SOURCE:
        raise SafeRaceError(f"{source!r} does not name the generic perception model")
    recipe = RECIPES.get(name or "default")
    if recipe is None:
        raise SafeRaceError(
            f"no perception recipe {name!r}: use {', '.join(PERCEPTION_RECIPES)} (generic:RECIPE)"
        )
    return recipe


def model_folder(recipe: PerceptionRecipe) -> Path:
    return cache_root() / "perception" / recipe.name


def model_path(recipe: PerceptionRecipe) -> Path:
    """The calibrated model of a recipe (it may not be built yet)."""
    return model_folder(recipe) / MODEL_FILE


def build_perception_model(
    recipe: PerceptionRecipe, workers: int = 1, progress: bool = True
) -> Path:
    """Build ``recipe``'s model (or finish an interrupted build) in its cache folder; its
    path. A built model is returned at once."""
    folder = model_folder(recipe)
    manifest_file = folder / MANIFEST_FILE
    check_recipe(recipe)
    if manifest_file.exists():
        return model_path(recipe)
    wanted = asdict(recipe)
    write_text_atomically(folder / RECIPE_FILE, json.dumps(wanted, indent=2) + "\n")
    stages = StageClock(folder / "seconds.json")
    with stages.timed("collect"):
        tracks = {part: write_tracks(recipe, part) for part in ("train", "calibration")}
        collect_all(recipe, tracks, workers, progress)
    with stages.timed("train"):
        state_file = train_state_network(recipe, tracks["train"], progress)
    with stages.timed("calibrate"):
        rows = calibrate_by_track(recipe, state_file, tracks)
    manifest = {
        "recipe": wanted,
        "track_seeds": {part: list(getattr(recipe, f"{part}_track_seeds")) for part in tracks},
        "seconds": stages.seconds(),
        "scale": max(row["own scale"] for row in rows),
        "calibration_by_track": rows,
        "files": {
            str(path.relative_to(folder)): sha256(path)
            for path in sorted(folder.rglob("*"))
            if path.is_file()
            and path.suffix in (".csv", ".npz", ".pt")
            and "resume" not in path.name
        },
        "saferace_version": __version__,
        "git_revision": git_revision(),
        "packages": package_versions(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    write_text_atomically(manifest_file, json.dumps(manifest, indent=2) + "\n")
    return model_path(recipe)


def check_recipe(recipe: PerceptionRecipe) -> None:
    """Raise where ``recipe``'s cache folder holds a build (or part of one) of another
    recipe of that name (one this version of SafeRace no longer makes)."""
    recipe_file = model_folder(recipe) / RECIPE_FILE
    wanted = json.loads(json.dumps(asdict(recipe)))
    if recipe_file.exists() and json.loads(recipe_file.read_text()) != wanted:
        raise SafeRaceError(
            f"{model_folder(recipe)} holds a build of another {recipe.name!r} recipe: delete "
            f"the folder and run saferace perception --recipe {recipe.name} to build this one"
        )


class StageClock:
    """Seconds spent per stage of a build, kept in ``path`` across interruptions (a resumed
    stage adds to what it took before)."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def seconds(self) -> dict[str, float]:
        return json.loads(self.path.read_text()) if self.path.exists() else {}

    @contextmanager
    def timed(self, stage: str) -> Iterator[None]:
        started = time.perf_counter()
        try:
            yield
        finally:
            spent = self.seconds()
            spent[stage] = spent.get(stage, 0.0) + time.perf_counter() - started
            write_text_atomically(self.path, json.dumps(spent, indent=2) + "\n")


def perception_manifest(recipe: PerceptionRecipe) -> dict:
    """The manifest of ``recipe``'s built model."""
    return json.loads((model_folder(recipe) / MANIFEST_FILE).read_text())


def write_tracks(recipe: PerceptionRecipe, part: str) -> list[Path]:
    """The ``part`` (train or calibration) tracks' CSVs, each of a random size and lane
    width (log-uniform in the recipe's range) drawn from its seed."""
    paths = []
    for seed in getattr(recipe, f"{part}_track_seeds"):
        path = track_file(recipe, f"{part}_{seed}")
        if not path.exists():
            radius, width = track_size(recipe, seed)
            write_random_track(path, seed, radius, lane_width_m=width)
        paths.append(path)
    return paths


def track_size(recipe: PerceptionRecipe, seed: int) -> tuple[float, float]:
    """``(radius_m, lane_width_m)`` of the recipe's random track ``seed``, log-uniform in
    the recipe's ranges: as many tracks of 5-10 m across (hairpins, the infield in view)
    as of 40-80 m (a circuit's long gentle bends, nothing but the lane in view)."""
    rng = np.random.default_rng([recipe.seed, seed])
    radius = float(np.exp(rng.uniform(*np.log(recipe.radius_range_m))))
    return radius, float(np.exp(rng.uniform(*np.log(recipe.lane_width_range_m))))


def track_file(recipe: PerceptionRecipe, name: str) -> Path:
    """The CSV of the recipe's track ``name`` (``train_SEED`` or ``calibration_SEED``)."""
    return model_folder(recipe) / "tracks" / f"{name}.csv"


def rounds_folder(recipe: PerceptionRecipe, track: Path) -> Path:
    return model_folder(recipe) / "rounds" / track.stem


def collect_all(
    recipe: PerceptionRecipe, tracks: dict[str, list[Path]], workers: int, progress: bool
) -> None:
    """Every track's drives not yet on disk, a track per job (``workers`` at once)."""
    todo = [
        (recipe, track, part, index)
        for part, part_tracks in tracks.items()
        for index, track in enumerate(part_tracks)
        if len(round_dirs_of(rounds_folder(recipe, track))) < len(recipe.drivers)
    ]
    total = sum(len(part) for part in tracks.values())
    with Progress(
        total, "perception data", "track", enabled=progress, initial=total - len(todo)
    ) as bar:
        run_jobs(
            collect_track,
            todo,
            lambda job, frames: None,
            workers=workers,
            advance=lambda job: bar.done(job[1].stem),
            describe=lambda job: job[1].stem,
        )


def round_dirs_of(folder: Path) -> list[Path]:
    return round_dirs(folder) if folder.exists() else []


def collect_track(recipe: PerceptionRecipe, track: Path, part: str, track_index: int) -> int:
    """Drive the remaining drives of ``track`` (the ``track_index``-th of ``part``), a
    round each; the frames written."""
    folder = rounds_folder(recipe, track)
    frames = 0
    for index, (driver, task, look) in enumerate(recipe.drives(part, track_index)):
        if index < len(round_dirs_of(folder)):
            continue
        seed = int(
            np.random.default_rng([recipe.seed, int(track.stem.split("_")[-1]), index]).integers(
                2**31
            )
        )
        config = CollectionConfig(
            agent=driver,
            task=task,
            track=str(track),
            seeds=(seed,),
            episode=EpisodeSettings(
                laps=10,
                max_seconds=recipe.seconds_per_drive,
                image_size=recipe.image_size,
                randomize=look,
            ),
            perturbation=Perturbation(steer_std_rad=recipe.steer_noise_rad),
            safety=FilterConfig() if driver == "expert" else FilterConfig(kind="cbf"),
        )
        frames += collect_round(folder, config, progress=False).frame_count
    return frames


def train_state_network(recipe: PerceptionRecipe, tracks: list[Path], progress: bool) -> Path:
    """The heteroscedastic state network trained on the train tracks' frames (resumable)."""
    path = model_folder(recipe) / "state_uncalibrated.pt"
    if path.exists():
        return path
    frames = targets_of(recipe, load_rounds([rounds_folder(recipe, track) for track in tracks]))
    config = TrainConfig(
        epochs=recipe.epochs,
        lr_schedule=recipe.lr_schedule,
        batch_size=recipe.batch_size,
        val_stretch=None,
        seed=recipe.seed,
        state_uncertainty="heteroscedastic",
        augment=True,
        networks=("state",),
    )
    resume = model_folder(recipe) / "training.resume"
    control, state, metadata = train_networks(frames, config, progress, resume, recipe.mirror)
    save_checkpoint(path, control, state, metadata)
    resume.unlink(missing_ok=True)
    return path


def calibrate_by_track(
    recipe: PerceptionRecipe, state_file: Path, tracks: dict[str, list[Path]]
) -> list[dict]:
    """Calibrate the network track by track on the calibration tracks (frames with the car
    inside its lane), its monitor's Gaussian fitted on training frames of the calibration
    looks (a look it was trained on but not calibrated for then raises it); write the
    model.
    The rows of the calibration tracks (read back where the model is written already)."""
    if model_path(recipe).exists():
        return load_checkpoint(model_path(recipe)).metadata[CONFORMAL_KEY]["groups"]
    loaded = load_checkpoint(state_file)
    calibration_frames = [
        inside_frames(recipe, rounds_folder(recipe, track), track)
        for track in tracks["calibration"]
    ]
    frames = FrameSet(
        {
            name: np.concatenate([part[name] for part in calibration_frames])
            for name in calibration_frames[0].arrays
        },
        [],
    )
    groups = np.concatenate(
        [
            np.full(len(part), track.stem)
            for part, track in zip(calibration_frames, tracks["calibration"], strict=True)
        ]
    )
    prediction = predict_frames(loaded.state, network_data(frames)["state"], 1)
    training = load_rounds([rounds_folder(recipe, track) for track in tracks["train"]])
    looks = np.array([manifest["config"]["randomize"] for manifest in training.manifests])
    training = training.subset(np.isin(looks[training["source"]], recipe.calibration_looks))
    chosen = np.random.default_rng(recipe.seed).permutation(len(training))[:MONITOR_FIT_FRAMES]
    reference = predict_frames(
        loaded.state, network_data(training.subset(np.sort(chosen)))["state"], 1
    )
    lane = slice(0, len(CALIBRATED_OUTPUTS))
    calibration, rows = group_calibration(
        prediction.mean[:, lane],
        prediction.std[:, lane],
        frames["state"][:, lane],
        groups,
        recipe.alpha,
        feature_monitor(reference.features, recipe.alpha),
        prediction.features,
    )
    record = {**calibration.as_dict(), "fitted_on": "calibration tracks, by track", "groups": rows}
    save_checkpoint(
        model_path(recipe),
        None,
        loaded.state,
        {**loaded.metadata, CONFORMAL_KEY: record, "perception_recipe": asdict(recipe)},
    )
    return rows


def inside_frames(recipe: PerceptionRecipe, folder: Path, track: Path) -> FrameSet:
    frames = load_rounds([folder])
    return targets_of(recipe, frames.subset(inside_lane(frames, Track.load(str(track)))))


def targets_of(recipe: PerceptionRecipe, frames: FrameSet) -> FrameSet:
    """``frames`` (of the recipe's tracks) with the state the network learns: with
    ``lane_middle``, ``e_y`` from the lane's middle (``saferace.safety.uncertainty.
    lane_middle``), by the widths of each frame's track at its arc length; with
    ``lane_fraction`` too, in units of the lane's half width there."""
    if not recipe.lane_middle:
        return frames
    state = frames["state"].copy()
    for source, manifest in enumerate(frames.manifests):
        rows = frames["source"] == source
        if rows.any():
            track = Track.load(str(track_file(recipe, Path(manifest["path"]).parent.name)))
            w_right, w_left = track.widths(frames["s_m"][rows])
            state[rows, 0] = lane_middle_state(
                state[rows, 0], w_left, w_right, per_half_width=recipe.lane_fraction
            )
    return FrameSet({**frames.arrays, "state": state}, frames.manifests)


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def generic_state_source(
    argument: str,
    image_shape: tuple[int, ...],
    n_samples: int = 1,
    seed: int | None = None,
    track: Track | None = None,
) -> ConformalStateSource:
    """``--state-source generic[:RECIPE]``: the built model of the recipe, with its
    calibration by track as interval and monitor, or with ``track`` its calibration on that
    track (:mod:`saferace.learning.track_calibration`, made once and cached)."""
    recipe = recipe_named(f"{GENERIC_SOURCE}:{argument}" if argument else GENERIC_SOURCE)
    path = model_path(recipe)
    if not (model_folder(recipe) / MANIFEST_FILE).exists():
        raise SafeRaceError(
            f"the generic perception model ({recipe.name} recipe) is not built: run "
            f"saferace perception --recipe {recipe.name} (it is cached in {model_folder(recipe)})"
        )
    check_recipe(recipe)
    loaded = load_checkpoint(path)
    check_generic_image_shape(recipe.name, tuple(loaded.metadata["image_shape"]), image_shape)
    source: StateSource = LearnedStateSource(
        loaded.state, n_samples, seed, checkpoint=loaded.describe()
    )
    if recipe.lane_middle:
        source = LaneMiddleStateSource(source, per_half_width=recipe.lane_fraction)
    if track is not None:  # (imported here: that module builds on this one)
        from saferace.learning.track_calibration import track_calibration

        return ConformalStateSource(source, track_calibration(recipe, track)[0])
    return ConformalStateSource(
        source, ConformalCalibration.from_dict(loaded.metadata[CONFORMAL_KEY])
    )


def ensure_perception_model(source: str | None, workers: int = 1) -> None:
    """Build the generic model a ``source`` names where it is not built yet (before any
    worker needs it); nothing for any other source."""
    if source is None or source.partition(":")[0] != GENERIC_SOURCE:
        return
    recipe = recipe_named(source)
    if (model_folder(recipe) / MANIFEST_FILE).exists():
        return
    LOG.warning(
        "building the generic perception model (%s recipe) once, into %s",
        recipe.name,
        model_folder(recipe),
    )
    started = time.perf_counter()
    build_perception_model(recipe, workers)
    LOG.warning("built in %s", duration_words(time.perf_counter() - started))
