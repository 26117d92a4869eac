"""The generic perception model calibrated on the user's own track, in about a minute.

The generic model's interval scale and monitor threshold are the largest of its calibration
tracks' (:mod:`saferace.learning.perception`): they hold on a new track exchangeable with
those random ones, which a user's circuit need not be. The map of the user's track is known,
though, and the expert can drive it: :func:`track_calibration` drives the expert with the
recipe's steering noise on the track, from starts spread evenly around the lap, taking turns
through the recipe's looks, and fits the track's own interval scale and monitor threshold
(split conformal, the frames inside the lane; the monitor's Gaussian stays the model's).

It reports the coverage and alarm rate of the pooled calibration and of the track's own on
drives the own calibration was not fitted on (the drives of one half of the starts are
scored with a calibration fitted on the other half); the calibration kept is then fitted on
all drives. It is cached per recipe by the track's fingerprint (a hash of the lane as
loaded), kept while the model file's hash and the drives are the same, so the next run on
the same track loads it.
"""

from __future__ import annotations

import fcntl
import json
import logging
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, cast

import gymnasium as gym
import numpy as np

from saferace.errors import SafeRaceError
from saferace.eval.agents import act, make_agent
from saferace.learning.agent import LearnedStateSource
from saferace.learning.checkpoint import CONFORMAL_KEY, load_checkpoint, write_text_atomically
from saferace.learning.collect import SteeringNoise
from saferace.learning.configs import Perturbation
from saferace.learning.perception import (
    MANIFEST_FILE,
    PerceptionRecipe,
    model_folder,
    model_path,
    sha256,
)
from saferace.progress import Progress
from saferace.safety.decision import nominal_parts
from saferace.safety.uncertainty.conformal import (
    ConformalCalibration,
    conformal_quantile,
    normalised_scores,
    stored_scores,
)
from saferace.safety.uncertainty.feature_monitor import FeatureMonitor
from saferace.safety.uncertainty.lane_middle import LaneMiddleStateSource
from saferace.safety.uncertainty.state_sources import true_lane_state
from saferace.track import Track

if TYPE_CHECKING:  # for typing only
    from saferace.envs.racing_env import RacingEnv

LOG = logging.getLogger(__name__)
#: Drives of the expert on the user's track, each from its own start, and their length.
DRIVES = 8
SECONDS_PER_DRIVE = 8.0
#: The lane outputs the interval is calibrated for: ``e_y``, ``e_psi`` (the curvature is
#: the map's).
LANE_OUTPUTS = 2
#: Frames inside the lane a track's calibration needs, at least (two conformal quantiles
#: at alpha 0.05 need 19 frames each to be finite).
MIN_FRAMES = 80
FRAME_NAMES = ("mean", "std", "truth", "features")


def calibration_file(recipe: PerceptionRecipe, track: Track) -> Path:
    """Where the recipe's calibration on ``track`` is cached: by the lane's fingerprint."""
    return model_folder(recipe) / "own_tracks" / f"{track.fingerprint[:24]}.json"


def track_calibration(
    recipe: PerceptionRecipe,
    track: Track,
    progress: bool = True,
    drives: int | None = None,
    seconds_per_drive: float | None = None,
) -> tuple[ConformalCalibration, dict]:
    """The recipe's built model calibrated on ``track`` and its report, from the cache or
    made now (under a lock: workers that start together make it once); ``drives`` and
    ``seconds_per_drive`` default to :data:`DRIVES` and :data:`SECONDS_PER_DRIVE`."""
    drives = DRIVES if drives is None else drives
    seconds_per_drive = SECONDS_PER_DRIVE if seconds_per_drive is None else seconds_per_drive
    if not (model_folder(recipe) / MANIFEST_FILE).exists():
        raise SafeRaceError(
            f"the generic perception model ({recipe.name} recipe) is not built: run "
            f"saferace perception --recipe {recipe.name}"
        )
    path = calibration_file(recipe, track)
    path.parent.mkdir(parents=True, exist_ok=True)
    model_hash = sha256(model_path(recipe))
    with open(path.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if path.exists():
            stored = json.loads(path.read_text())
            made = (stored["model_sha256"], stored["drives"], stored["seconds_per_drive"])
            if made == (model_hash, drives, seconds_per_drive):
                return ConformalCalibration.from_dict(stored["calibration"]), stored["report"]
        calibration, report = fit_track_calibration(
            recipe, track, progress, drives, seconds_per_drive
        )
        record = {
            "track": track.name,
            "fingerprint": track.fingerprint,
            "model_sha256": model_hash,
            "drives": drives,
            "seconds_per_drive": seconds_per_drive,
            "calibration": calibration.as_dict(),
            "report": report,
        }
        write_text_atomically(path, json.dumps(record, indent=2) + "\n")
    return calibration, report


def fit_track_calibration(
    recipe: PerceptionRecipe,
    track: Track,
    progress: bool,
    drives: int,
    seconds_per_drive: float,
) -> tuple[ConformalCalibration, dict]:
    """Drive, predict and fit (see the module): the track's calibration and its report."""
    loaded = load_checkpoint(model_path(recipe))
    pooled = ConformalCalibration.from_dict(loaded.metadata[CONFORMAL_KEY])
    network = LearnedStateSource(loaded.state, 1, recipe.seed)
    source = LaneMiddleStateSource(network, per_half_width=recipe.lane_fraction)
    frames: dict[int, dict[str, np.ndarray]] = {}
    with Progress(drives, f"calibrating on {track.name}", "drive", enabled=progress) as bar:
        for index in range(drives):
            drive = drive_frames(recipe, track, index, drives, seconds_per_drive, source, network)
            if drive is not None:
                frames[index] = drive
            bar.done(f"start at {index / drives:.0%} of the lap")
    count = sum(len(drive["truth"]) for drive in frames.values())
    if count < MIN_FRAMES or len({index % 2 for index in frames}) < 2:
        raise SafeRaceError(
            f"only {count} frames inside the lane of {track.name}: the expert could not "
            "drive it; check the track with saferace tracks"
        )
    return calibration_from_drives(pooled, frames)


def calibration_from_drives(
    pooled: ConformalCalibration, drives: dict[int, dict[str, np.ndarray]]
) -> tuple[ConformalCalibration, dict]:
    """The track's own calibration from its ``drives`` (by index: each's frames' ``mean``,
    ``std`` and ``truth`` of the lane outputs and ``features``), the ``pooled`` one's
    monitor refitted, and the report: the pooled and the own calibration's coverage and
    alarm rate on the odd drives, the own one fitted on the even drives for that."""
    monitor = pooled.monitor
    if not isinstance(monitor, FeatureMonitor):
        raise SafeRaceError("the generic model's calibration has no feature monitor to refit")
    frames = {name: np.concatenate([d[name] for d in drives.values()]) for name in FRAME_NAMES}
    scores = normalised_scores(frames["mean"], frames["std"], frames["truth"])
    monitor_scores = monitor.scores(frames["features"])
    even = np.concatenate([np.full(len(d["truth"]), index % 2 == 0) for index, d in drives.items()])
    held_out = ~even
    half_scale = conformal_quantile(scores[even], pooled.alpha)
    half_threshold = conformal_quantile(monitor_scores[even], pooled.alpha)
    threshold = conformal_quantile(monitor_scores, pooled.alpha)
    own = ConformalCalibration(
        pooled.alpha,
        conformal_quantile(scores, pooled.alpha),
        len(scores),
        replace(monitor, threshold=threshold),
        stored_scores(scores),
    )
    report = {
        "frames": len(scores),
        "held_out_frames": int(held_out.sum()),
        "pooled": {
            "scale": pooled.scale,
            "threshold": monitor.threshold,
            "coverage": float(np.mean(scores[held_out] <= pooled.scale)),
            "alarm_rate": float(np.mean(monitor_scores[held_out] > monitor.threshold)),
        },
        "own": {
            "scale": own.scale,
            "threshold": threshold,
            "coverage": float(np.mean(scores[held_out] <= half_scale)),
            "alarm_rate": float(np.mean(monitor_scores[held_out] > half_threshold)),
        },
    }
    LOG.info("own-track calibration: %s", report)
    return own, report


def drive_frames(
    recipe: PerceptionRecipe,
    track: Track,
    index: int,
    drives: int,
    seconds: float,
    source: LaneMiddleStateSource,
    network: LearnedStateSource,
) -> dict[str, np.ndarray] | None:
    """The ``index``-th of ``drives``, ``seconds`` long: the expert with steering noise from
    ``index / drives`` of the lap, in the recipe's looks by turns; per frame inside the
    lane, the model's mean and spread of ``[e_y, e_psi]`` (in metres from the centre line),
    the truth and the backbone's features (None: no frame inside the lane)."""
    look = recipe.looks[index % len(recipe.looks)]
    env = gym.make(
        "saferace/CenterLine-v0",
        track=track,
        image_size=(recipe.image_size, recipe.image_size),
        randomize=look,
    )
    seed = int(np.random.default_rng([recipe.seed, index]).integers(2**31))
    expert = make_agent("expert", env, seed=seed)
    base = cast("RacingEnv", env.unwrapped)
    noise = SteeringNoise(
        Perturbation(steer_std_rad=recipe.steer_noise_rad), base.control_dt_s, seed
    )
    observation, info = env.reset(seed=seed, options={"start_s_m": index * track.length_m / drives})
    source.reset(seed)
    rows: dict[str, list] = {name: [] for name in FRAME_NAMES}
    action_space = base.action_space
    assert isinstance(action_space, gym.spaces.Box), "SafeRace tasks act in a Box"
    low, high = action_space.low, action_space.high
    for _ in range(round(seconds / base.control_dt_s)):
        samples = np.atleast_2d(source.samples(observation, info))
        if not info["outside_lane"]:
            rows["mean"].append(samples.mean(axis=0)[:LANE_OUTPUTS])
            rows["std"].append(samples.std(axis=0)[:LANE_OUTPUTS])
            rows["truth"].append(true_lane_state(info)[:LANE_OUTPUTS])
            rows["features"].append(np.asarray(network.last_features, float))
        action = nominal_parts(act(expert, observation, info))[0].copy()
        action[0] += noise.sample()
        observation, _, terminated, truncated, info = env.step(
            np.clip(action, low, high).astype(np.float32)
        )
        if terminated or truncated:
            break
    env.close()
    if not rows["truth"]:
        return None
    return {name: np.array(values, float) for name, values in rows.items()}
