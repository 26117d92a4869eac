"""The learned driver and the perceived state: both networks plugged into the suite.

:class:`LearnedAgent` drives from the observation alone (image and velocities; it never
reads ``info``): the control network's MC-dropout mean steering and target speed, the
target speed through the PID speed loop to ``accel_mps2``, handed to a safety filter as a
:class:`~saferace.safety.decision.NominalAction` with the network's spread, so that the
filter's QP bends the control the network is least sure of (paper's final QP).
:class:`LearnedStateSource` gives the filter the state network's MC-dropout samples of
``[e_y, e_psi, kappa]``: the perceived state (paper Sec. 3.4), from the image alone.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np
import torch

from saferace.agents.pid import PIDGains, PIDSpeedController
from saferace.errors import SafeRaceError
from saferace.learning.checkpoint import CONFORMAL_KEY, LearnedCheckpoint, load_checkpoint
from saferace.learning.cpu_compile import compile_enabled, eager_calls
from saferace.learning.ensemble import StateNetwork
from saferace.learning.networks import DrivingNetwork, Prediction
from saferace.safety.decision import NominalAction
from saferace.safety.uncertainty.conformal import ConformalCalibration
from saferace.safety.uncertainty.intervals import ConformalStateSource

if TYPE_CHECKING:  # for typing only: importing saferace.envs sets up MuJoCo's OpenGL
    from saferace.envs.racing_env import RacingEnv

#: Streams of dropout masks drawn from one episode seed: the agent's and the state source's.
AGENT_STREAM, STATE_STREAM = 0, 1


def dropout_seed(seed: int | None, stream: int) -> int:
    """The seed of one stream of dropout masks for an episode seed (None: seed 0)."""
    sequence = np.random.SeedSequence([0 if seed is None else seed, stream])
    return int(sequence.generate_state(1)[0])


class LearnedAgent:
    """The control network ``M_com`` with a PID speed loop; ``act(obs, info)`` ignores info.

    Its MC-dropout masks come from a generator seeded by the episode's ``seed`` at each
    reset: the same seed gives the same episode.
    """

    def __init__(
        self,
        network: DrivingNetwork,
        speed_controller: PIDSpeedController,
        mc_samples: int = 10,
        seed: int | None = None,
        checkpoint: dict | None = None,
    ) -> None:
        if mc_samples < 1:
            raise SafeRaceError(f"mc_samples must be at least 1, got {mc_samples}")
        self.network = network
        self.speed_controller = speed_controller
        self.mc_samples = mc_samples
        self.checkpoint = checkpoint or {}
        self._seed = seed
        self._generator = torch.Generator()
        self.reset()

    def reset(self) -> None:
        self.speed_controller.reset()
        self._generator.manual_seed(dropout_seed(self._seed, AGENT_STREAM))

    def act(self, observation: dict[str, np.ndarray], info: Any = None) -> NominalAction:
        velocity = observation["velocity"]
        prediction = self.network.predict(
            observation["image"], velocity, self.mc_samples, self._generator
        )
        return self._action(prediction.mean[0], prediction.std[0], velocity)

    def _action(self, mean: np.ndarray, std: np.ndarray, velocity: np.ndarray) -> NominalAction:
        """The nominal action from the network's mean and spread: the PID loop turns the
        target speed into an acceleration (and its spread, by the loop's gain)."""
        (steer, target_speed), (steer_std, speed_std) = mean, std
        accel = self.speed_controller.command(target_speed, float(velocity[0]))
        accel_std = self.speed_controller.gains.kp_per_s * speed_std
        return NominalAction(
            np.array([steer, accel], dtype=float), np.array([steer_std, accel_std], dtype=float)
        )

    @staticmethod
    def act_together(
        agents: list[LearnedAgent], observations: list[dict[str, np.ndarray]]
    ) -> list[NominalAction]:
        """What each agent would do on its observation, from one forward pass of their
        shared network: each draws its own dropout masks, as it would alone (the features
        of a batch agree with one frame's to float rounding, not bit for bit)."""
        network = agents[0].network
        if any(agent.network is not network for agent in agents):
            raise SafeRaceError("agents driven together must share one network")
        if len({agent.mc_samples for agent in agents}) != 1:
            raise SafeRaceError("agents driven together must take the same MC samples")
        images = np.stack([observation["image"] for observation in observations])
        velocities = np.stack([observation["velocity"] for observation in observations])
        generators = [agent._generator for agent in agents]
        with eager_calls():  # a batch, even of the one episode still running
            prediction = network.predict(images, velocities, agents[0].mc_samples, generators)
        return [
            agent._action(prediction.mean[k], prediction.std[k], velocities[k])
            for k, agent in enumerate(agents)
        ]

    def describe(self) -> dict:
        """What a result row records: the checkpoint and the number of MC samples."""
        return {**self.checkpoint, "mc_samples": self.mc_samples}


class LearnedStateSource:
    """The state network ``M_st``'s MC-dropout samples of ``[e_y, e_psi, kappa]``.

    Implements :class:`~saferace.safety.uncertainty.state_sources.StateSource` from the image alone;
    ``info`` is never read. Dropout masks come from a generator seeded at each reset, so
    the same episode seed gives the same samples. ``last_features``: the backbone features
    of the last frame, for a feature monitor
    (:class:`~saferace.safety.uncertainty.intervals.FeatureSource`).
    """

    def __init__(
        self,
        network: StateNetwork,
        n_samples: int = 10,
        seed: int | None = None,
        checkpoint: dict | None = None,
    ) -> None:
        if n_samples < 1:
            raise SafeRaceError(f"n_samples must be at least 1, got {n_samples}")
        self.network = network
        self.n_samples = n_samples
        self.checkpoint = checkpoint or {}
        self.last_features: np.ndarray | None = None
        self._seed = seed
        self._generator = torch.Generator()
        self._pool: ThreadPoolExecutor | None = None
        self._pending: tuple[dict, Future[Prediction]] | None = None
        self.reset(seed)

    def reset(self, seed: int | None = None) -> None:
        self._settled()  # a prediction under way draws no masks after the reseeding
        chosen = self._seed if seed is None else seed
        self._generator.manual_seed(dropout_seed(chosen, STATE_STREAM))

    def prefetch(self, observation: dict[str, np.ndarray]) -> None:
        """Start predicting ``observation`` in a background thread, which :meth:`samples`
        then takes: the agent's network runs beside it (the filter calls this when a step
        returns an observation). The background thread predicts with the calling thread's
        number of PyTorch threads (each thread has its own), so the results are the ones
        the calling thread would get, whatever the timing. On the CPU only: on a GPU two
        threads would capture CUDA graphs at once. One network only: an ensemble (deep, MIMO
        or packed) beside the agent's network fought it for the cores (on 2 cores the step
        with a deep ensemble ran at 22 steps/s instead of 29, with a packed one at 57
        instead of 68; with MC dropout at 84 instead of 65). Eager networks only: two
        networks compiled for the CPU (:mod:`~saferace.learning.cpu_compile`) side by side
        fought for the cores too (MC dropout's step: 76 steps/s, one after the other 149)."""
        one_network = isinstance(self.network, DrivingNetwork) and self.network.config.members == 1
        device = self.network.device
        if not one_network or device.type != "cpu" or compile_enabled(device):
            return
        self._settled()
        if self._pool is None:
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="state-source")
        threads, image = torch.get_num_threads(), observation["image"]
        self._pending = (observation, self._pool.submit(self._predict, image, threads))

    def samples(self, observation: dict[str, np.ndarray], info: Any = None) -> np.ndarray:
        prefetched = self._settled()
        prediction = (
            prefetched[1]
            if prefetched is not None and prefetched[0] is observation
            else self._predict(observation["image"])
        )
        self.last_features = prediction.features[0]
        return prediction.samples[0]

    def _predict(self, image: np.ndarray, threads: int | None = None) -> Prediction:
        """The network's prediction, on ``threads`` PyTorch threads (None: this thread's)."""
        if threads is not None:
            torch.set_num_threads(threads)
        return self.network.predict(image, None, self.n_samples, self._generator)

    def _settled(self) -> tuple[dict, Prediction] | None:
        """The prefetched observation and its prediction, once done (None if none)."""
        pending, self._pending = self._pending, None
        return None if pending is None else (pending[0], pending[1].result())

    def __getstate__(self) -> dict[str, Any]:
        """A copy without the thread, once the prediction under way is done (this one still
        takes it)."""
        if self._pending is not None:
            self._pending[1].result()
        return {**self.__dict__, "_pool": None, "_pending": None}

    def describe(self) -> dict:
        return {**self.checkpoint, "mc_samples": self.n_samples}


def learned_agent(
    env: gym.Env, checkpoint: str | Path, mc_samples: int = 10, seed: int | None = None
) -> LearnedAgent:
    """``learned:CHECKPOINT``: the checkpoint's control network driving ``env``."""
    loaded = load_checkpoint(checkpoint)
    if loaded.control is None:
        raise SafeRaceError(
            f"{checkpoint} is a perception model: it holds a state network and no control "
            "network to drive with (use it as a --state-source)"
        )
    observation_space = env.observation_space
    assert isinstance(observation_space, gym.spaces.Dict), "SafeRace observations are a Dict"
    image_shape = observation_space["image"].shape
    assert image_shape is not None, "SafeRace images are a Box, with a shape"
    check_image_shape(loaded, image_shape)
    base = cast("RacingEnv", env.unwrapped)  # a SafeRace task
    low, high = base.action_space.low, base.action_space.high
    gains = PIDGains(min_accel_mps2=float(low[1]), max_accel_mps2=float(high[1]))
    controller = PIDSpeedController(base.control_dt_s, gains)
    return LearnedAgent(loaded.control, controller, mc_samples, seed, loaded.describe())


def learned_state_source(
    checkpoint: str | Path,
    image_shape: tuple[int, ...],
    n_samples: int = 10,
    seed: int | None = None,
) -> LearnedStateSource | ConformalStateSource:
    """``--state-source learned:CHECKPOINT``: the checkpoint's state network, for a task
    whose images have ``image_shape``; with the checkpoint's conformal calibration (see
    ``saferace calibrate``), if it has one, as its interval and monitor."""
    loaded = load_checkpoint(checkpoint)
    recipe = loaded.metadata.get("perception_recipe", {})
    if recipe.get("lane_middle"):
        raise SafeRaceError(
            f"{checkpoint} is the generic perception model of the {recipe['name']!r} recipe: its "
            "e_y is measured from the lane's middle, which only it moves back to the centre "
            f"line: name it --state-source generic:{recipe['name']}"
        )
    check_image_shape(loaded, image_shape)
    source = LearnedStateSource(loaded.state, n_samples, seed, checkpoint=loaded.describe())
    calibration = loaded.metadata.get(CONFORMAL_KEY)
    if calibration is None:
        return source
    return ConformalStateSource(source, ConformalCalibration.from_dict(calibration))


def check_image_shape(checkpoint: LearnedCheckpoint, image_shape: tuple[int, ...]) -> None:
    """Raise unless images of ``image_shape`` are what the networks were trained on."""
    trained = tuple(checkpoint.metadata["image_shape"])
    if tuple(image_shape) != trained:
        hint = "add --stereo" if trained[-1] == 6 else "drop --stereo"
        raise SafeRaceError(
            f"checkpoint {checkpoint.path} was trained on images {trained}, not "
            f"{tuple(image_shape)}: use the same --image-size and camera ({hint} if only the "
            "channels differ)"
        )


def check_generic_image_shape(
    recipe: str, trained: tuple[int, ...], image_shape: tuple[int, ...]
) -> None:
    """Refuse, in one line naming what works, images the generic perception model of the
    ``recipe`` was not ``trained`` on (one mono camera at one size: a stereo pair or another
    size would have to be a recipe of its own)."""
    if tuple(image_shape) == trained:
        return
    height, width, channels = trained
    fixes = []
    if tuple(image_shape)[-1] != channels:
        fixes.append("drop --stereo")
    if tuple(image_shape)[:2] != (height, width):
        fixes.append(f"use --image-size {height}")
    raise SafeRaceError(
        f"the generic perception model ({recipe} recipe) reads mono {height}x{width} "
        f"images, not {tuple(image_shape)}: {' and '.join(fixes)}, or feed the filter "
        "another state source (--state-source learned:CKPT, a network trained on these "
        "images, or noisy or oracle)"
    )
