"""Record a collection round: any driver drives, the expert MPC labels every frame.

Every frame carries the onboard image and velocities, what the driver did, the expert's
label ``[steer_rad, target_speed_mps, accel_mps2]`` for the state the car is really in, and
the true lane state, whoever drove (paper Sec. 2.3: the expert labels, the learner drives).
A steering perturbation (DART, Laskey et al. 2017) makes the driver act with noise while the
label stays the expert's, so that the data show recoveries from where the noise led.
DAgger's options (paper Sec. 2.3): ``train_fraction`` keeps only the frames on the first
part of the lap for training (the rest of the lap is for testing: its frames go to the
round's held-out file, for scoring and calibrating the networks, never for training), and
``beta`` lets the expert act in place of the driver on that share of the steps (a mixing
schedule; the paper uses none).
"""

from __future__ import annotations

import math
import multiprocessing
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from saferace.agents.mpc import TARGET_SPEED_LOOKAHEAD_S, MPCExpert
from saferace.envs.unwrap import racing_env
from saferace.errors import SafeRaceError
from saferace.eval.agents import Agent, act, make_agent
from saferace.eval.metrics import span_metrics, thinned_trajectory
from saferace.eval.parallel import available_cores, limit_threads, run_jobs
from saferace.eval.runner import (
    EpisodeResult,
    git_revision,
    make_task_env,
    max_steps_for,
    package_versions,
    run_episode,
)
from saferace.eval.vector_runner import (
    act_all_agents,
    run_together,
    share_networks,
    worker_context,
)
from saferace.learning.configs import CollectionConfig, Perturbation
from saferace.learning.expert_labels import ExpertLabels, LabelsFromInfo, labelling_expert
from saferace.learning.rounds import FRAME_FIELDS, write_round
from saferace.progress import Progress
from saferace.safety.decision import NominalAction, nominal_parts
from saferace.safety.uncertainty.state_sources import true_lane_state
from saferace.version import __version__


class SteeringNoise:
    """Samples of a :class:`Perturbation` at the control period, from a seeded generator."""

    def __init__(self, perturbation: Perturbation, dt_s: float, seed: int | None) -> None:
        self.std = perturbation.steer_std_rad
        self.decay = math.exp(-dt_s / perturbation.correlation_time_s)
        self._seed = seed
        self.reset()

    def reset(self) -> None:
        self._rng = np.random.default_rng(self._seed)
        self._value = self.std * self._rng.standard_normal() if self.std else 0.0

    def sample(self) -> float:
        """The next value (rad); starts from the stationary distribution."""
        if not self.std:
            return 0.0
        value = self._value
        innovation = math.sqrt(1.0 - self.decay**2) * self.std * self._rng.standard_normal()
        self._value = self.decay * value + innovation
        return value


class LabellingDriver:
    """Drives with ``driver`` (or the expert itself) plus noise; records expert-labelled frames.

    Pass it to :func:`~saferace.eval.runner.run_episode` as the agent and its
    :meth:`after_step` as ``on_step``: a frame is recorded before each step and completed
    with the action the car got (after any filter) once the step is done.
    """

    def __init__(
        self,
        expert: MPCExpert,
        driver: Agent | Callable | None,
        noise: SteeringNoise,
        action_space: gym.spaces.Box,
        episode: int = 0,
        beta: float = 0.0,
        seed: int | None = None,
    ) -> None:
        self.expert, self.driver, self.noise = expert, driver, noise
        self.action_low, self.action_high = action_space.low, action_space.high
        self.frames: dict[str, list] = {name: [] for name in FRAME_FIELDS}
        self.episode = episode
        self.beta = beta
        self._seed = seed
        self.reset()

    def reset(self) -> None:
        self.expert.reset()
        self.noise.reset()
        self._mixing = np.random.default_rng(self._seed)
        if self.driver is not None and hasattr(self.driver, "reset"):
            self.driver.reset()

    def act(
        self, observation: dict[str, np.ndarray], info: dict[str, Any]
    ) -> np.ndarray | NominalAction:
        driver = self.driver
        driver_action = (
            act(driver, observation, info) if driver is not None and self.driver_acts() else None
        )
        return self.labelled(observation, info, driver_action)

    def driver_acts(self) -> bool:
        """Whether the driver acts this step (else the expert): a draw of the mixing
        schedule, taken before the driver is asked (so that drivers can be asked together,
        :func:`act_labellers`)."""
        return self.driver is not None and not (self.beta and self._mixing.random() < self.beta)

    def labelled(
        self, observation: dict[str, np.ndarray], info: dict[str, Any], driver_action: Any
    ) -> np.ndarray | NominalAction:
        """Record the frame with the expert's label; the action: the driver's (None: the
        expert's) with the steering noise."""
        expert_action = self.expert.act(observation, info)
        label = (expert_action[0], self.expert.planned_speed_mps(), expert_action[1])
        action = expert_action if driver_action is None else driver_action
        mean, std = nominal_parts(action)
        mean = mean.copy()
        mean[0] += self.noise.sample()
        frames = self.frames
        frames["image"].append(observation["image"])
        frames["velocity"].append(observation["velocity"])
        frames["driver_action"].append(mean)
        frames["expert"].append(label)
        frames["state"].append(true_lane_state(info))
        frames["s_m"].append(info["s_m"])
        frames["time_s"].append(info["time_s"])
        frames["episode"].append(self.episode)
        return mean if std is None else NominalAction(mean, std)

    def after_step(self, observation: dict, info: dict[str, Any], action: Any) -> None:
        """Complete the last frame with the applied action and the filter's intervention."""
        safety = info.get("safety")
        if safety is None:
            applied = np.clip(nominal_parts(action)[0], self.action_low, self.action_high)
        else:
            applied = np.asarray(safety["filtered_action"])
        self.frames["applied_action"].append(applied)
        self.frames["intervened"].append(bool(safety and safety["intervened"]))

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: np.asarray(values) for name, values in self.frames.items()}


@dataclass(frozen=True)
class CollectedRound:
    """Where a round was written, its size and each episode's lap summary."""

    path: Path
    frame_count: int
    episodes: list[dict]


@dataclass(frozen=True)
class CollectedEpisode:
    """One episode of a round: its kept and held-out frames and its summary."""

    frames: dict[str, np.ndarray]
    held_out: dict[str, np.ndarray]
    summary: dict
    track_name: str
    track_length_m: float
    control_hz: float


def collect_round(
    dataset_dir: str | Path,
    config: CollectionConfig,
    progress: bool = True,
    workers: int = 1,
    ray_address: str | None = None,
    num_envs: int = 1,
) -> CollectedRound:
    """Drive one episode per seed, label every frame, write it all as the next round.

    Each episode's summary holds its lap metrics, those of the part of the lap past
    ``train_fraction`` (``held_out``, when it is below 1) and a downsampled trajectory.
    The episodes are independent: ``workers`` processes or Ray tasks (``ray_address``,
    see :func:`~saferace.eval.parallel.run_jobs`) drive them at once, or ``num_envs`` > 1
    of them at a time run together (:func:`collect_episodes_together`: in lockstep for
    learned drivers, else each driven through in a worker); the round is the same as a
    serial one.
    """
    if num_envs > 1 and (workers > 1 or ray_address is not None):
        raise SafeRaceError("choose --num-envs or --workers/--ray: both drive episodes at once")
    collected: dict[int, CollectedEpisode] = {}
    if num_envs > 1:
        seeds = list(config.seeds)
        for start in range(0, len(seeds), num_envs):
            group = range(start, min(start + num_envs, len(seeds)))
            episodes = collect_episodes_together(config, list(group), progress)
            collected.update(zip(group, episodes, strict=True))
    else:
        jobs = [
            (config, episode, seed, progress and workers <= 1)
            for episode, seed in enumerate(config.seeds)
        ]
        run_jobs(
            collect_episode,
            jobs,
            lambda job, result: collected.__setitem__(job[1], result),
            workers=workers,
            ray_address=ray_address,
            describe=lambda job: f"episode {job[1]} (seed {job[2]})",
        )
    episodes = [collected[episode] for episode in range(len(config.seeds))]
    arrays, held_out_arrays = (
        {name: np.concatenate([getattr(e, part)[name] for e in episodes]) for name in FRAME_FIELDS}
        for part in ("frames", "held_out")
    )
    summaries = [episode.summary for episode in episodes]
    manifest_config = {
        **config.as_dict(),
        "track": episodes[0].track_name,
        "track_argument": str(config.track),
        "track_length_m": episodes[0].track_length_m,
        "control_hz": episodes[0].control_hz,
        "label_lookahead_s": TARGET_SPEED_LOOKAHEAD_S,
        "episodes": summaries,
        "saferace_version": __version__,
        "git_revision": git_revision(),
        "packages": package_versions(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    path = write_round(dataset_dir, arrays, manifest_config, held_out_arrays)
    return CollectedRound(path, len(arrays["s_m"]), summaries)


def collect_episode(
    config: CollectionConfig, episode: int, seed: int, progress: bool = False
) -> CollectedEpisode:
    """Drive and label episode ``episode`` of a round (seeded by ``seed``)."""
    env = task_env(config, seed)
    try:
        expert = labelling_expert(env, config.episode.expert_model)
        labeller = labelling_driver(config, env, expert, episode, seed)
        result = run_episode(
            env, labeller, seed=seed, progress=progress, on_step=labeller.after_step
        )
    finally:
        env.close()
    return collected_episode(config, env, labeller, result, seed)


def collect_episodes_together(
    config: CollectionConfig, episodes: list[int], progress: bool = False
) -> list[CollectedEpisode]:
    """Drive and label ``episodes`` of a round at once. Drivers that can act together
    (:meth:`~saferace.learning.agent.LearnedAgent.act_together`) drive in lockstep, one
    batched forward pass per step, the envs (each with the expert that labels it,
    :class:`~saferace.learning.expert_labels.ExpertLabels`) in worker processes
    (:func:`~saferace.eval.vector_runner.run_together`); the others, with nothing to batch,
    each drive their episode through in a worker (:func:`collect_episodes_apart`)."""
    seeds = [config.seeds[episode] for episode in episodes]
    like = task_env(config, seeds[0])
    try:
        labellers = [
            labelling_driver(config, like, LabelsFromInfo(), episode, seed)
            for episode, seed in zip(episodes, seeds, strict=True)
        ]
        if not drive_in_lockstep(labellers):
            return collect_episodes_apart(config, episodes, progress)
        share_networks([labeller.driver for labeller in labellers])
        make_envs = [
            partial(labelled_task_env, config, seed, config.episode.expert_model) for seed in seeds
        ]
        results = run_together(
            make_envs,
            labellers,
            seeds,
            like,
            act_labellers,
            [labeller.after_step for labeller in labellers],
            progress,
            preload=(ExpertLabels.__module__,),
        )
    finally:
        like.close()
    return [
        collected_episode(config, like, labeller, result, seed)
        for labeller, result, seed in zip(labellers, results, seeds, strict=True)
    ]


def drive_in_lockstep(labellers: Sequence[LabellingDriver]) -> bool:
    """Whether a round's drivers gain from lockstep: some act together in one batched
    forward pass (learned agents)."""
    return any(hasattr(labeller.driver, "act_together") for labeller in labellers)


def collect_episodes_apart(
    config: CollectionConfig, episodes: list[int], progress: bool = False
) -> list[CollectedEpisode]:
    """``episodes`` each driven through by :func:`collect_episode` in a worker process, as
    many at a time as there are cores: the serial episodes' frames by construction. For
    drivers that act alone (the expert, scripted agents), where lockstep buys nothing: on 2
    cores 8 expert-driven episodes in lockstep ran at 1.0x the serial frames/s (8 workers)
    and 1.2-1.5x (2 workers of 4 envs), since each step's hand-overs left the cores idle;
    driven through, at about 1.8x."""
    jobs = [(config, episode, config.seeds[episode]) for episode in episodes]
    context = multiprocessing.get_context(worker_context((ExpertLabels.__module__,)))
    workers = min(len(jobs), available_cores())
    collected = []
    with (
        context.Pool(workers, initializer=limit_threads, initargs=(1,)) as pool,
        Progress(len(jobs), f"{len(jobs)} episodes", "episode", enabled=progress) as bar,
    ):
        for episode in pool.imap(_collect_job, jobs):
            collected.append(episode)
            bar.update()
    return collected


def _collect_job(job: tuple[CollectionConfig, int, int]) -> CollectedEpisode:
    return collect_episode(*job)


def act_labellers(
    labellers: Sequence[LabellingDriver], observations: Sequence[dict], infos: Sequence[dict]
) -> list:
    """Every labeller's action; the drivers that act this step asked together where they
    can be (one batched forward pass), else one by one."""
    acting = [labeller.driver_acts() for labeller in labellers]
    asked = [k for k, acts in enumerate(acting) if acts]
    answers = act_all_agents(
        [labellers[k].driver for k in asked],
        [observations[k] for k in asked],
        [infos[k] for k in asked],
    )
    driver_actions: list[Any] = [None] * len(labellers)
    for k, answer in zip(asked, answers, strict=True):
        driver_actions[k] = answer
    return [
        labeller.labelled(observation, info, driver_action)
        for labeller, observation, info, driver_action in zip(
            labellers, observations, infos, driver_actions, strict=True
        )
    ]


def task_env(config: CollectionConfig, seed: int) -> gym.Env:
    """The env an episode of ``config`` is driven in (with its filter, if any)."""
    settings = config.episode
    return make_task_env(
        config.task,
        config.track,
        settings.laps,
        config.safety,
        seed,
        max_steps=max_steps_for(settings.max_seconds),
        image_size=(settings.image_size, settings.image_size),
        stereo=settings.stereo,
        randomize=settings.randomize,
        **({"opponents": list(config.opponents)} if config.opponents else {}),
    )


def labelled_task_env(config: CollectionConfig, seed: int, expert_model: str) -> gym.Env:
    """:func:`task_env` with the expert's labels in its infos (a vector's worker's env)."""
    return ExpertLabels(task_env(config, seed), expert_model)


def labelling_driver(
    config: CollectionConfig, env: gym.Env, expert: Any, episode: int, seed: int
) -> LabellingDriver:
    """The labeller of episode ``episode``: ``config``'s driver (None: the expert) with its
    steering noise and mixing, labelled by ``expert``."""
    settings = config.episode
    base = racing_env(env)
    driver = (
        None
        if config.agent == "expert"
        else make_agent(config.agent, env, settings.expert_model, settings.mc_samples, seed)
    )
    noise = SteeringNoise(config.perturbation, base.control_dt_s, seed)
    return LabellingDriver(expert, driver, noise, base.action_space, episode, config.beta, seed)


def collected_episode(
    config: CollectionConfig,
    env: gym.Env,
    labeller: LabellingDriver,
    result: EpisodeResult,
    seed: int,
) -> CollectedEpisode:
    """An episode's frames split at ``train_fraction`` of the lap, and its summary."""
    settings, base = config.episode, racing_env(env)
    track_length = base.track.length_m
    frames = labeller.arrays()
    kept = np.mod(frames["s_m"] / track_length, 1.0) < settings.train_fraction
    return CollectedEpisode(
        frames={name: values[kept] for name, values in frames.items()},
        held_out={name: values[~kept] for name, values in frames.items()},
        summary=episode_summary(
            seed, result, track_length, settings.train_fraction, base.control_dt_s
        ),
        track_name=base.track.name,
        track_length_m=track_length,
        control_hz=1.0 / base.control_dt_s,
    )


def episode_summary(
    seed: int, result: EpisodeResult, track_length_m: float, train_fraction: float, dt_s: float
) -> dict:
    """What a round's manifest keeps of one episode: lap metrics, the held-out part's, and
    the path driven (at most about 500 points)."""
    steps = result.steps
    summary = {
        "seed": seed,
        **result.summary,
        "terminated": result.terminated,
        "duration_s": len(steps["s_m"]) * dt_s,
    }
    if train_fraction < 1.0:
        held_out = np.mod(steps["s_m"] / track_length_m, 1.0) >= train_fraction
        summary["held_out"] = (
            span_metrics(steps, held_out, dt_s) if held_out.any() else {"steps": 0}
        )
    summary["trajectory"] = thinned_trajectory(steps, ("x_m", "y_m", "s_m"))
    return summary
