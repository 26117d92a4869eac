"""Several episodes driven at once through gymnasium's vector API, each as it would run alone.

:func:`run_together` steps N environments in lockstep in worker processes
(``gymnasium.vector.AsyncVectorEnv``), so that their physics, rendering and filters run side
by side, while the agents act in this process, where ``act_all`` may answer all of them
with one batched forward pass. There are as many workers as cores (at most N), each
stepping its share of the envs one after another (:class:`VectorGroup`): on 2 cores 8
envs in 8 workers ran no faster than one env alone (each worker's step took 1.75 ms
instead of 1.2, and every step woke all of them at once), in 2 workers of 4 each 1.2-1.5x
as fast. (A collection whose drivers act alone skips lockstep:
:func:`~saferace.learning.collect.collect_episodes_apart`.) Each episode keeps the
records of :func:`~saferace.eval.runner.run_episode` and, with the same seed and agent, the
same steps: an episode that ends waits (:class:`VectorSlot` replays its last step without
simulating) until every one has.

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
from saferace.eval.parallel import available_cores, limit_threads
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
    """One env's step info, carried whole through the vector, with whether its episode
    ended there."""

    __slots__ = ("info", "terminated", "truncated")

    def __init__(self, info: dict, terminated: bool = False, truncated: bool = False) -> None:
        self.info = info
        self.terminated = terminated
        self.truncated = truncated


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
        mean, std = decoded(action)
        given = mean if std is None else NominalAction(mean, std)
        observation, reward, terminated, truncated, info = self.env.step(given)
        if terminated or truncated:
            describe = getattr(getattr(self.env, "state_source", None), "describe", None)
            info = {**info, SOURCE_KEY: None if describe is None else describe()}
        box = InfoBox(info, bool(terminated), bool(truncated))
        result = (observation, reward, terminated, truncated, {INFO_KEY: box})
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


def decoded(row: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`encoded`'s mean and spread (None where it has none)."""
    mean, std = np.split(np.asarray(row[1:], dtype=float), 2)
    return mean, std if row[0] > 0.0 else None


def worker_context(preload: Sequence[str] = ()) -> str:
    """``fork`` where this process has neither rendered nor loaded PyTorch, else
    ``forkserver`` (its server preloading :data:`PRELOADED`, ``preload`` and the main
    module)."""
    if not has_rendered() and "torch" not in sys.modules:
        return "fork"
    # where no server runs yet; with the main module, which each worker would import again
    multiprocessing.set_forkserver_preload(["__main__", *PRELOADED, *preload])
    return "forkserver"


class VectorGroup(gym.Env):
    """A worker's share of a vector's envs, each in a :class:`VectorSlot` seeded with its own
    seed, stepped one after another: observations a tuple of the envs' own, actions one row
    per env (``width`` rows, the rest ignored), the info each env's :class:`InfoBox` under
    :data:`INFO_KEY`; it ends when all have. The envs are built at the first reset, in the
    worker with one thread for its libraries (gymnasium builds a first group in the parent
    only for its spaces)."""

    def __init__(
        self,
        make_envs: Sequence[Callable[[], gym.Env]],
        seeds: Sequence[int],
        observation_space: gym.Space,
        width: int,
        action_size: int,
    ) -> None:
        self.observation_space = gym.spaces.Sequence(observation_space)
        self.action_space = gym.spaces.Box(-np.inf, np.inf, (width, action_size), np.float64)
        self._make_envs, self._seeds = list(make_envs), list(seeds)
        self._slots: list[VectorSlot] = []

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple:
        if not self._slots:
            if multiprocessing.parent_process() is not None:
                limit_threads(1)
            self._slots = [VectorSlot(make()) for make in self._make_envs]
        outcomes = [slot.reset(seed=s) for slot, s in zip(self._slots, self._seeds, strict=True)]
        return tuple(o for o, _ in outcomes), {INFO_KEY: [i[INFO_KEY] for _, i in outcomes]}

    def step(self, action: np.ndarray) -> tuple:
        outcomes = [slot.step(a) for slot, a in zip(self._slots, action, strict=False)]
        boxes = [info[INFO_KEY] for *_, info in outcomes]
        ended = all(box.terminated or box.truncated for box in boxes)
        return tuple(o[0] for o in outcomes), 0.0, ended, False, {INFO_KEY: boxes}

    def close(self) -> None:
        for slot in self._slots:
            slot.close()


def worker_shares(count: int, workers: int) -> list[range]:
    """``count`` envs dealt to at most ``workers`` workers in contiguous runs, as evenly as
    can be (8 on 2: 4 and 4; 5 on 2: 3 and 2)."""
    workers = max(1, min(count, workers))
    sizes = [count // workers + (w < count % workers) for w in range(workers)]
    starts = np.cumsum([0, *sizes])
    return [range(start, start + size) for start, size in zip(starts, sizes, strict=False)]


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
    shares = worker_shares(count, available_cores())
    width = max(len(share) for share in shares)
    rows = [(w, j) for w, share in enumerate(shares) for j in range(len(share))]  # env k's
    try:
        vector = gym.vector.AsyncVectorEnv(
            [
                partial(
                    VectorGroup,
                    [make_envs[k] for k in share],
                    [seeds[k] for k in share],
                    like.observation_space,
                    width,
                    encoded_size(like),
                )
                for share in shares
            ],
            shared_memory=False,
            context=worker_context(preload),
            autoreset_mode=AutoresetMode.DISABLED,
        )
        batched, infos = vector.reset()
        observations = [observation for group in batched for observation in group]
        step_infos = [box.info for boxes in infos[INFO_KEY] for box in boxes]
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
                actions = np.zeros((len(shares), width, encoded_size(like)))
                for k, action in zip(active, chosen, strict=True):
                    actions[rows[k]] = encoded(action, filtered)
                batched, _, _, _, infos = vector.step(actions)
                observations = [observation for group in batched for observation in group]
                boxes = [box for group_boxes in infos[INFO_KEY] for box in group_boxes]
                for k in active:
                    info = step_infos[k] = boxes[k].info
                    recorders[k].record(info)
                    if on_steps is not None:
                        mean = decoded(actions[rows[k]])[0]
                        applied = info["safety"]["filtered_action"] if filtered else mean
                        on_steps[k](observations[k], info, np.asarray(applied, dtype=float))
                    if boxes[k].terminated or boxes[k].truncated:
                        ends[k] = (info, boxes[k].terminated, boxes[k].truncated)
                        bar.update(base.max_steps - len(recorders[k].records["s_m"]))
                bar.update(len(active))
            results = []
            for recorder, end in zip(recorders, ends, strict=True):
                assert end is not None, "every episode has ended"
                results.append(recorder.result(*end))
                results[-1].source_description = end[0][SOURCE_KEY]
            for seed, result in zip(seeds, results, strict=True):
                words = episode_words(result.summary, result.ending)
                bar.report(f"episode (seed {seed})", words, False)
    finally:
        if vector is not None:
            vector.close()
    return results
