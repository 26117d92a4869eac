"""A learned state source starts on each observation early; its results do not change."""

from __future__ import annotations

import threading

import gymnasium as gym
import numpy as np
import pytest
import torch

import saferace  # noqa: F401  - registers the tasks
from saferace.learning.agent import LearnedStateSource
from saferace.learning.networks import DrivingNetwork, state_config
from saferace.names import COMPILE_VARIABLE
from saferace.safety.cbf.filter import SafetyFilter

TIMES = ("solve_time_s", "filter_time_s")


def drive(steps: int, seed: int) -> tuple[list[dict], LearnedStateSource]:
    torch.manual_seed(0)
    source = LearnedStateSource(DrivingNetwork(state_config()).eval(), 10, seed=seed)
    env = SafetyFilter(gym.make("saferace/CenterLine-v0", track="lab"), state_source=source)
    observation, _ = env.reset(seed=seed)
    assert source._pending is None or source._pending[0] is observation
    decisions = []
    for _ in range(steps):
        observation, _, _, _, info = env.step(np.array([0.02, 0.5]))
        decisions.append({k: v for k, v in info["safety"].items() if k not in TIMES})
    env.close()
    return decisions, source


def in_other_thread(function, *args) -> None:
    thread = threading.Thread(target=function, args=args)
    thread.start()
    thread.join()


def test_prefetched_samples_are_the_ones_asked_for_at_the_step(monkeypatch: pytest.MonkeyPatch):
    # This thread's own count set, another thread's set to 1 sets that of threads started
    # later (the background one): the prediction must still be this thread's.
    threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    in_other_thread(torch.set_num_threads, 1)
    try:
        prefetched, source = drive(6, seed=3)
    finally:
        in_other_thread(torch.set_num_threads, threads)
    assert source._pending is not None  # the last observation is under way
    monkeypatch.setattr(LearnedStateSource, "prefetch", lambda self, observation: None)
    asked, _ = drive(6, seed=3)
    assert prefetched == asked
    assert len({str(d["state_mean"]) for d in asked}) > 1  # the samples move step to step


def test_a_reset_waits_for_the_prediction_under_way_before_reseeding():
    _, source = drive(3, seed=5)
    image = np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)
    source.prefetch({"image": image})
    source.reset(5)
    after_reset = source.samples({"image": image})
    torch.manual_seed(0)
    fresh = LearnedStateSource(DrivingNetwork(state_config()).eval(), 10, seed=5)
    assert np.array_equal(after_reset, fresh.samples({"image": image}))


def test_samples_of_another_observation_than_the_prefetched_one_are_its_own():
    torch.manual_seed(0)
    network = DrivingNetwork(state_config()).eval()
    images = np.random.default_rng(1).integers(0, 255, (2, 64, 64, 3), dtype=np.uint8)
    early = LearnedStateSource(network, 10, seed=2)
    early.prefetch({"image": images[0]})
    other = early.samples({"image": images[1]})
    plain = LearnedStateSource(network, 10, seed=2)
    plain.samples({"image": images[0]})  # the masks the prefetch drew
    assert np.array_equal(other, plain.samples({"image": images[1]}))


def test_a_network_compiled_for_the_cpu_is_not_prefetched(monkeypatch: pytest.MonkeyPatch):
    source = LearnedStateSource(DrivingNetwork(state_config()).eval(), 10, seed=0)
    image = np.zeros((64, 64, 3), np.uint8)
    monkeypatch.setenv(COMPILE_VARIABLE, "1")  # side by side, compiled networks fight
    source.prefetch({"image": image})
    assert source._pending is None
    monkeypatch.setenv(COMPILE_VARIABLE, "0")
    source.prefetch({"image": image})
    assert source._pending is not None
