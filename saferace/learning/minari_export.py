"""Export collection and DAgger rounds as a Minari dataset, the Farama format for offline RL.

Each episode of a round becomes one Minari episode. A round stores, per control step, the
onboard observation and the action applied after it, but not the observation after the
last step, which Minari requires: an episode of N frames therefore becomes N observations
and N - 1 steps (its last action is dropped). The step's ``action`` is the one the car got
(``applied_action``: after a safety filter, if any); the infos, one per observation, keep
everything else a round records: the expert's label ``expert`` ``[steer_rad,
target_speed_mps, accel_mps2]``, the true Frenet state ``state`` ``[e_y_m, e_psi_rad,
kappa_radpm]``, ``driver_action``, ``applied_action``, ``s_m``, ``time_s`` and
``intervened``. Rewards are the task's (``progress_m - deviation_m ** 2``, see
:class:`~saferace.envs.racing_env.RacingEnv`), recomputed from the recorded states.
Images are stored losslessly (no JPEG), so frames load back bit for bit. Every episode
ends truncated: the step that may have terminated it is the one dropped.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

import gymnasium as gym
import numpy as np

from saferace.errors import SafeRaceError
from saferace.extras import require
from saferace.learning.rounds import FRAME_FIELDS, round_dirs, round_episodes

INFO_FIELDS = tuple(name for name in FRAME_FIELDS if name not in ("image", "velocity", "episode"))


def export_minari(
    rounds: Sequence[str | Path],
    dataset_id: str,
    datasets_dir: str | Path | None = None,
    description: str | None = None,
):
    """Write the episodes of ``rounds`` (round or dataset folders) as the Minari dataset
    ``dataset_id`` (under ``datasets_dir``, else Minari's own root); the ``MinariDataset``."""
    minari = require("minari", "minari", "exporting rounds as a Minari dataset")
    EpisodeBuffer = require("minari.data_collector", "minari", "the Minari export").EpisodeBuffer

    folders = [folder for path in rounds for folder in round_dirs(path)]
    if not folders:
        raise SafeRaceError(
            f"no complete collection round at {', '.join(map(str, rounds))}: expected "
            "dataset folders with round_NNNN/ folders or round folders"
        )
    buffers, settings, drivers, revisions = [], set(), set(), set()
    for folder in folders:
        manifest, episodes = round_episodes(folder)
        config = manifest["config"]
        drivers.add(config["agent"])
        revisions.add(f"saferace {config['saferace_version']} (git {config['git_revision']})")
        look = config.get("randomize", "none")
        settings.add(
            (config["task"], config["track_argument"], tuple(manifest["image_shape"]), look)
        )
        rewards = _rewards(config)
        seeds = [episode["seed"] for episode in config["episodes"]]
        for frames in episodes:
            if len(frames["s_m"]) < 2:
                continue  # a one-frame episode has no step
            buffers.append(_episode_buffer(EpisodeBuffer, frames, seeds, rewards))
    if len(settings) > 1:
        raise SafeRaceError(
            "a Minari dataset holds one task, track and camera; these rounds mix "
            + "; ".join(
                f"{task} on {track} with {shape} images, {look} looks"
                for task, track, shape, look in settings
            )
        )
    (task, track, image_shape, look) = settings.pop()
    with _datasets_root(datasets_dir):
        if dataset_id in minari.list_local_datasets():
            raise SafeRaceError(
                f"a Minari dataset {dataset_id!r} exists already; delete it first "
                f"(minari delete {dataset_id}) or give another name"
            )
        spec = _env_spec(task, track, image_shape, look)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="`author_email` is set to None")
            return minari.create_dataset_from_buffers(
                dataset_id=dataset_id,
                buffer=buffers,
                env=spec,
                eval_env=spec,
                code_permalink=", ".join(sorted(revisions)),
                algorithm_name=f"SafeRace rounds driven by {', '.join(sorted(drivers))}, "
                "labelled by the MPC expert",
                author="SafeRace",
                description=description or _description(folders, task, track),
                data_format="hdf5",
                jpeg_encoding=False,
            )


def _episode_buffer(buffer_type, frames: dict, seeds: list[int], rewards):
    """One Minari episode of a round's episode (see the module docstring)."""
    count = len(frames["s_m"])
    episode = int(frames["episode"][0])
    truncations = np.zeros(count - 1, bool)
    truncations[-1] = True  # the episode's last step, which may have ended it, is dropped
    return buffer_type(
        seed=seeds[episode],
        observations={"image": frames["image"], "velocity": frames["velocity"]},
        actions=frames["applied_action"][:-1],
        rewards=rewards(frames),
        terminations=np.zeros(count - 1, bool),
        truncations=truncations,
        infos={name: frames[name] for name in INFO_FIELDS},
    )


def _rewards(config: dict):
    """The task's reward of each step of a round's episode, from its recorded states."""
    from saferace.envs.reference_lines import reference_line
    from saferace.track import Track
    from saferace.track.frenet import wrap_arc

    try:
        track = Track.load(config["track_argument"])
    except (OSError, SafeRaceError) as error:
        raise SafeRaceError(
            f"the rounds' track {config['track_argument']!r} cannot be loaded to compute the "
            f"rewards: {error}"
        ) from error
    reference = reference_line(track, "racing" if config["task"] == "RacingLine" else "center")

    def rewards(frames: dict) -> np.ndarray:
        s = frames["s_m"].astype(float)
        progress = wrap_arc(np.diff(s), track.length_m)
        deviation = frames["state"][1:, 0] - reference.offset_at(s[1:])
        return progress - deviation**2

    return rewards


def _env_spec(
    task: str, track: str, image_shape: Sequence[int], look: str
) -> gym.envs.registration.EnvSpec:
    """The spec that makes the env the rounds were driven in (``recover_environment``)."""
    from saferace.eval.runner import task_id

    height, width, channels = image_shape
    kwargs = {
        "track": str(track),
        "image_size": [height, width],
        "stereo": channels == 6,
        "randomize": look,
    }
    return dataclasses.replace(gym.spec(task_id(task)), kwargs=kwargs)


def _description(folders: list[Path], task: str, track: str) -> str:
    return (
        f"{len(folders)} SafeRace collection round(s) of saferace/{task}-v0 on {track}; "
        "infos hold the expert's labels [steer_rad, target_speed_mps, accel_mps2] and the "
        "true state [e_y_m, e_psi_rad, kappa_radpm] of every observation."
    )


@contextlib.contextmanager
def _datasets_root(datasets_dir: str | Path | None) -> Iterator[None]:
    """Minari's dataset root set to ``datasets_dir`` (if given) for the block."""
    if datasets_dir is None:
        yield
        return
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(Path(datasets_dir).resolve())
    try:
        yield
    finally:
        if before is None:
            del os.environ["MINARI_DATASETS_PATH"]
        else:
            os.environ["MINARI_DATASETS_PATH"] = before
