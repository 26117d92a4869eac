"""Episodes collected together (``--num-envs``) give the frames they give one by one."""

from __future__ import annotations

import copy

import gymnasium as gym
import numpy as np
import pytest
import torch

from saferace.agents.pid import PIDSpeedController
from saferace.errors import SafeRaceError
from saferace.eval import vector_runner
from saferace.eval.vector_runner import VectorSlot, encoded, worker_shares
from saferace.learning import collect
from saferace.learning.agent import LearnedAgent
from saferace.learning.collect import collect_episode, collect_episodes_together, collect_round
from saferace.learning.configs import CollectionConfig, EpisodeSettings, Perturbation
from saferace.learning.networks import DrivingNetwork, control_config
from saferace.learning.rounds import load_rounds
from saferace.safety.decision import NominalAction, nominal_parts
from tests.cli_helpers import run_cli


def short_config(**overrides) -> CollectionConfig:
    values = dict(
        agent="drift",
        task="CenterLine",
        track="lab",
        seeds=(3, 4, 5),
        episode=EpisodeSettings(max_seconds=1.5, train_fraction=0.5, randomize="mild"),
        perturbation=Perturbation(0.05),
        beta=0.5,
    )
    return CollectionConfig(**{**values, **overrides})


@pytest.mark.parametrize("lockstep", [False, True])
def test_episodes_driven_together_give_the_serial_frames_bit_for_bit(lockstep, monkeypatch):
    # A scripted driver drives its episodes through in workers; in lockstep (what learned
    # drivers get), 3 envs on 2 workers, one of them stepping 2 envs one after the other.
    monkeypatch.setattr(collect, "drive_in_lockstep", lambda labellers: lockstep)
    monkeypatch.setattr(vector_runner, "available_cores", lambda: 2)
    config = short_config()  # a driver, the expert's mixing and steering noise all drawn
    serial = [collect_episode(config, episode, seed) for episode, seed in enumerate(config.seeds)]
    together = collect_episodes_together(config, [0, 1, 2])
    for alone, batched in zip(serial, together, strict=True):
        for part in ("frames", "held_out"):
            for name, values in getattr(alone, part).items():
                assert np.array_equal(values, getattr(batched, part)[name]), (part, name)
        assert alone.summary == batched.summary
    assert not np.array_equal(serial[0].frames["image"], serial[1].frames["image"][:1])
    assert len({tuple(episode.frames["driver_action"][:, 0][:5]) for episode in serial}) == 3


def test_envs_are_dealt_to_the_workers_in_even_contiguous_runs():
    def sizes(count: int, workers: int) -> list[tuple[int, int]]:
        return [(share.start, len(share)) for share in worker_shares(count, workers)]

    assert sizes(8, 2) == [(0, 4), (4, 4)]
    assert sizes(5, 2) == [(0, 3), (3, 2)]
    assert sizes(3, 8) == [(0, 1), (1, 1), (2, 1)]
    assert sizes(1, 2) == [(0, 1)]


def test_a_round_collected_in_groups_is_the_serial_round(tmp_path):
    config = short_config(agent="expert", seeds=(1, 2, 3), beta=0.0)
    serial = load_rounds([collect_round(tmp_path / "serial", config, progress=False).path])
    grouped = collect_round(tmp_path / "grouped", config, progress=False, num_envs=2).path
    together = load_rounds([grouped])
    for name in ("image", "state", "expert", "applied_action", "episode"):
        assert np.array_equal(serial[name], together[name]), name
    with pytest.raises(SafeRaceError, match="num-envs"):
        collect_round(tmp_path / "both", config, progress=False, workers=2, num_envs=2)


def learned_agents(count: int) -> list[LearnedAgent]:
    torch.manual_seed(0)
    network = DrivingNetwork(control_config()).eval()
    return [LearnedAgent(network, PIDSpeedController(0.05), 10, seed) for seed in range(count)]


def test_learned_agents_acting_together_draw_their_own_masks_in_one_forward_pass():
    agents = learned_agents(3)
    alone = copy.deepcopy(agents)
    alone_network = alone[0].network
    for agent in alone:
        agent.network = alone_network  # deepcopy keeps one network shared too
    rng = np.random.default_rng(0)
    observations = [
        {"image": rng.integers(0, 255, (64, 64, 3), dtype=np.uint8),
         "velocity": np.array([2.0 + k, 0.0, 0.1], np.float32)}
        for k in range(3)
    ]  # fmt: skip
    for _ in range(2):  # the masks move on as they would alone
        together = LearnedAgent.act_together(agents, observations)
        each = [
            agent.act(observation) for agent, observation in zip(alone, observations, strict=True)
        ]
        for batched, single in zip(together, each, strict=True):
            np.testing.assert_allclose(batched.mean, single.mean, atol=1e-5)
            np.testing.assert_allclose(batched.std, single.std, atol=1e-5)
    assert not np.allclose(together[0].std, together[1].std)  # each its own masks
    with pytest.raises(SafeRaceError, match="share one network"):
        LearnedAgent.act_together([agents[0], learned_agents(1)[0]], observations[:2])


def test_collect_takes_num_envs(tmp_path):
    result = run_cli(
        "collect", "--track", "lab", "--seeds", "0", "1", "--max-seconds", "1",
        "--num-envs", "2", "--out", str(tmp_path / "data"),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert load_rounds([tmp_path / "data"])["episode"].max() == 1


def test_eval_rows_of_episodes_driven_together_are_the_serial_rows(tmp_path, monkeypatch):
    from saferace.eval.filters import FilterConfig
    from saferace.eval.runner import evaluate

    monkeypatch.setattr(vector_runner, "available_cores", lambda: 2)  # 3 envs on 2 workers
    kwargs = dict(laps=1, progress=False, env_kwargs={"max_steps": 30, "randomize": "mild"})
    safety = FilterConfig(kind="cbf", state_noise=(0.05, 0.05))  # seeded by each seed
    threads = torch.get_num_threads()
    serial = evaluate("weave", "CenterLine", "lab", [0, 1, 2], safety=safety, **kwargs)
    together = evaluate(
        "weave", "CenterLine", "lab", [0, 1, 2], safety=safety, num_envs=3, **kwargs
    )
    assert torch.get_num_threads() == threads  # the workers' limit stays theirs
    for alone, grouped in zip(serial, together, strict=True):
        for key in ("summary", "trajectory", "config", "state_source"):
            assert alone.get(key) == grouped.get(key), key
    assert serial[0]["trajectory"] != serial[1]["trajectory"]
    result = run_cli(
        "eval", "--agent", "pure-pursuit", "--track", "lab", "--seeds", "0", "1",
        "--max-seconds", "1", "--num-envs", "2", "--out", str(tmp_path / "rows.jsonl"),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert len((tmp_path / "rows.jsonl").read_text().splitlines()) == 2


class Recording(gym.Env):
    """Keeps the action it was given; ends after one step."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,))
    action_space = gym.spaces.Box(-1.0, 1.0, (2,))

    def reset(self, *, seed=None, options=None):
        return np.zeros(1, np.float32), {}

    def step(self, action):
        self.action = action
        return np.zeros(1, np.float32), 0.0, True, False, {}


@pytest.mark.parametrize(
    "action, filtered",
    [
        (np.array([0.1, -0.5]), True),
        (NominalAction(np.array([0.1, -0.5]), np.array([0.02, 0.3])), True),
        (NominalAction(np.array([0.1, -0.5]), np.array([np.nan, np.nan])), True),
        (NominalAction(np.array([0.1, -0.5]), np.array([0.02, 0.3])), False),
    ],
)
def test_a_slot_hands_its_env_the_action_as_a_serial_run_would(action, filtered):
    slot = VectorSlot(Recording())
    slot.reset()
    slot.step(encoded(action, filtered))
    given = slot.env.action
    mean, std = nominal_parts(action)
    if filtered and std is not None:
        assert isinstance(given, NominalAction)
        np.testing.assert_array_equal(given.mean, mean)
        np.testing.assert_array_equal(given.std, std)  # NaN where it was NaN
    else:
        assert not isinstance(given, NominalAction)
        np.testing.assert_array_equal(given, mean)
    assert slot.step(encoded(action, filtered))[2] and slot.env.action is given  # held


class Counting(gym.Env):
    """Observes its step count; ends after as many steps as its seed."""

    observation_space = gym.spaces.Box(0.0, 100.0, (1,))
    action_space = gym.spaces.Box(-1.0, 1.0, (2,))

    def reset(self, *, seed=None, options=None):
        self.steps, self.length = 0, seed
        return np.zeros(1, np.float32), {"steps": 0}

    def step(self, action):
        self.steps += 1
        observation = np.full(1, self.steps, np.float32)
        return observation, 0.0, self.steps == self.length, False, {"steps": self.steps}


def test_a_group_keeps_an_ended_episode_still_until_all_have_ended():
    group = vector_runner.VectorGroup(
        [Counting, Counting], [1, 3], Counting.observation_space, 3, 5
    )
    observations, infos = group.reset()
    assert [box.info["steps"] for box in infos[vector_runner.INFO_KEY]] == [0, 0]
    seen = []
    for _ in range(3):
        observations, _, ended, _, infos = group.step(np.zeros((3, 5)))  # a padded row
        boxes = infos[vector_runner.INFO_KEY]
        seen.append(([float(o[0]) for o in observations], [b.terminated for b in boxes], ended))
    assert seen == [
        ([1.0, 1.0], [True, False], False),
        ([1.0, 2.0], [True, False], False),  # the first answers with its last step
        ([1.0, 3.0], [True, True], True),
    ]
