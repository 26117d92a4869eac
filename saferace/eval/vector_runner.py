"""Several episodes driven at once through gymnasium's vector API, each as it would run alone.

:func:`run_together` steps N environments in lockstep, each in its own process
(``gymnasium.vector.AsyncVectorEnv``), so that their physics, rendering and filters run side
by side,
while the agents act in this process, where ``act_all`` may answer all of them with one
batched forward pass. Each episode keeps the records of :func:`~saferace.eval.runner.
run_episode` and, with the same seed and agent, the same steps: an episode that ends waits
(:class:`VectorSlot` replays its last step without simulating) until every one has.

The workers are forked from this process where it has neither rendered nor loaded
PyTorch: they start at once, with every module imported (a collection driven by the
expert). Elsewhere (a child forked from a process that did would share its OpenGL and
PyTorch state) they fork from a server process that has imported the modules they need
(the scenes, the filters, the expert: seconds of imports a spawned worker would pay each,
:data:`PRELOADED`) and the main module (which a worker imports again otherwise: a script
that imports PyTorch cost each of 8 workers 0.7 s more). Each worker gets one thread
for BLAS, OpenMP and PyTorch (N busy workers each starting a thread per core fight over the
cores).
"""

from __future__ import annotations

import multiprocessing
import sys
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode

from saferace.envs.gl_backend import has_rendered
from saferace.envs.unwrap import racing_env
from saferace.eval.agents import act
from saferace.eval.parallel import limit_threads
from saferace.eval.runner import EpisodeRecorder, EpisodeResult, episode_words
from saferace.progress import Progress
from saferace.safety.decision import NominalAction, nominal_parts

#: The last info of an episode holds its state source's description under this key.
SOURCE_KEY = "state_source_description"
#: What the workers' server imports once, before it forks them.
PRELOADED = ("saferace.eval.runner", "saferace.agents.mpc")

#: ``info`` of a :class:`VectorSlot` step holds the episode's own info under this key, in
#: an :class:`InfoBox` (gymnasium would turn each field of a dict into an array).
INFO_KEY = "episode"


class InfoBox:
    """One env's step info, carried whole through the vector."""

    __slots__ = ("info",)

    def __init__(self, info: dict) -> None:
        self.info = info


class VectorSlot(gym.Wrapper):
    """One env of a vector: takes an agent's action as ``[has std, mean, std]`` (see
    :func:`encoded`), returns its info whole under :data:`INFO_KEY` (the last one with its
    state source's description under :data:`SOURCE_KEY`), and once its episode has ended
    answers every further step with its last one, without simulating."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.action_space = gym.spaces.Box(-np.inf, np.inf, (encoded_size(env),), np.float64)
        self._last: tuple | None = None

    def reset(self, **kwargs: Any) -> tuple[Any, dict]:
        self._last = None
        observation, info = self.env.reset(**kwargs)
        return observation, {INFO_KEY: InfoBox(info)}

    def step(self, action: np.ndarray) -> tuple:
        if self._last is not None:
            return self._last
        has_std, (mean, std) = action[0] > 0.0, np.split(np.asarray(action[1:], dtype=float), 2)
        decoded = NominalAction(mean, std) if has_std else mean
        observation, reward, terminated, truncated, info = self.env.step(decoded)
        if terminated or truncated:
            describe = getattr(getattr(self.env, "state_source", None), "describe", None)
            info = {**info, SOURCE_KEY: None if describe is None else describe()}
        result = (observation, reward, terminated, truncated, {INFO_KEY: InfoBox(info)})
        if terminated or truncated:
            self._last = result
        return result


def encoded_size(env: gym.Env) -> int:
    """The length of ``env``'s actions as a :class:`VectorSlot` takes them: a flag, the mean
    and the std."""
    shape = env.action_space.shape
    assert shape is not None, "SafeRace actions are a Box"
    return 1 + 2 * int(np.prod(shape))


def encoded(action: Any, filtered: bool) -> np.ndarray:
    """An agent's action as a :class:`VectorSlot` takes it: whether it has a spread (only a
    filter takes one), its mean and its spread (zeros where it has none)."""
    mean, std = nominal_parts(action)
    has_std = filtered and std is not None
    return np.concatenate([[float(has_std)], mean, std if has_std else np.zeros_like(mean)])


def worker_context(preload: Sequence[str] = ()) -> str:
    """``fork`` where this process has neither rendered nor loaded PyTorch, else
    ``forkserver`` (its server preloading :data:`PRELOADED`, ``preload`` and the main
    module)."""
    if not has_rendered() and "torch" not in sys.modules:
        return "fork"
    # where no server runs yet; with the main module, which each worker would import again
    multiprocessing.set_forkserver_preload(["__main__", *PRELOADED, *preload])
    return "forkserver"


def vector_slot(make_env: Callable[[], gym.Env]) -> VectorSlot:
    """A worker's env: one thread for its libraries, then ``make_env()`` in a slot (gymnasium
    also builds the first in this process, for its spaces: its threads stay as they are)."""
    if multiprocessing.parent_process() is not None:
        limit_threads(1)
    return VectorSlot(make_env())


def per_env(observations: dict[str, np.ndarray], count: int) -> list[dict[str, np.ndarray]]:
    """A vector's batched observations as one dict per env (copies)."""
    return [
        {key: np.array(values[k]) for key, values in observations.items()} for k in range(count)
    ]


ActAll = Callable[[Sequence[Any], Sequence[dict], Sequence[dict]], list]


def act_all_agents(
    agents: Sequence[Any], observations: Sequence[dict], infos: Sequence[dict]
) -> list:
    """Every agent's action: in one batched forward pass where all are learned agents of
    one network (their class's ``act_together``), else each on its own observation."""
    kind = type(agents[0]) if agents else None
    if (
        hasattr(kind, "act_together")
        and all(type(agent) is kind for agent in agents)
        and len({id(agent.network) for agent in agents}) == 1
    ):
        return kind.act_together(list(agents), list(observations))  # type: ignore[union-attr]
    return [act(agent, o, i) for agent, o, i in zip(agents, observations, infos, strict=True)]


def share_networks(agents: Sequence[Any]) -> None:
    """Give learned agents of one checkpoint (each loaded its own copy) the first one's
    network, so that they act in one forward pass."""
    learned = [agent for agent in agents if hasattr(agent, "act_together")]
    for agent in learned[1:]:
        if type(agent) is type(learned[0]) and agent.checkpoint == learned[0].checkpoint:
            agent.network = learned[0].network


def run_together(
    make_envs: Sequence[Callable[[], gym.Env]],
    agents: Sequence[Any],
    seeds: Sequence[int],
    like: gym.Env,
    act_all: ActAll = act_all_agents,
    on_steps: Sequence[Callable[[dict, dict, np.ndarray], None]] | None = None,
    progress: bool = False,
    preload: Sequence[str] = (),
) -> list[EpisodeResult]:
    """Drive ``agents[k]`` on ``make_envs[k]()`` (seeded ``seeds[k]``), all at once; each
    one's :class:`~saferace.eval.runner.EpisodeResult` as :func:`~saferace.eval.runner.
    run_episode` gives it. ``like``: an env built as the others (not stepped), to read what
    to record; ``act_all(agents, observations, infos)``: the active agents' actions
    (default :func:`act_all_agents`, after :func:`share_networks`);
    ``on_steps[k]``: as ``run_episode``'s ``on_step``, for env ``k``; ``preload``: modules
    the workers need beyond :data:`PRELOADED` (see :func:`worker_context`)."""
    count = len(make_envs)
    share_networks(agents)
    recorders = [EpisodeRecorder(like) for _ in range(count)]
    filtered = recorders[0].filtered
    base = racing_env(like)
    ends: list[tuple[dict, bool, bool] | None] = [None] * count
    vector = None
    try:
        vector = gym.vector.AsyncVectorEnv(
            [partial(vector_slot, make) for make in make_envs],
            shared_memory=False,
            context=worker_context(preload),
            autoreset_mode=AutoresetMode.DISABLED,
        )
        batched, infos = vector.reset(seed=list(seeds))
        observations = per_env(batched, count)
        step_infos = [box.info for box in infos[INFO_KEY]]
        for agent in agents:
            if hasattr(agent, "reset"):
                agent.reset()
        total = base.max_steps * count
        with Progress(total, f"{count} envs", "step", enabled=progress) as bar:
            while any(end is None for end in ends):
                active = [k for k in range(count) if ends[k] is None]
                chosen = act_all(
                    [agents[k] for k in active],
                    [observations[k] for k in active],
                    [step_infos[k] for k in active],
                )
                actions = np.zeros((count, encoded_size(like)))
                for k, action in zip(active, chosen, strict=True):
                    actions[k] = encoded(action, filtered)
                batched, _, terminated, truncated, infos = vector.step(actions)
                observations = per_env(batched, count)
                for k in active:
                    info = step_infos[k] = infos[INFO_KEY][k].info
                    recorders[k].record(info)
                    if on_steps is not None:
                        mean = actions[k][1 : 1 + (len(actions[k]) - 1) // 2]
                        applied = info["safety"]["filtered_action"] if filtered else mean
                        on_steps[k](observations[k], info, np.asarray(applied, dtype=float))
                    if terminated[k] or truncated[k]:
                        ends[k] = (info, bool(terminated[k]), bool(truncated[k]))
                        bar.update(base.max_steps - len(recorders[k].records["s_m"]))
                bar.update(len(active))
            results = []
            for recorder, end in zip(recorders, ends, strict=True):
                assert end is not None, "every episode has ended"
                results.append(recorder.result(*end))
                results[-1].source_description = end[0][SOURCE_KEY]
            for seed, result in zip(seeds, results, strict=True):
                bar.report(f"episode (seed {seed})", episode_words(result.summary), False)
    finally:
        if vector is not None:
            vector.close()
    return results
