"""Environment steps per second: physics only, 64x64 mono, 64x64 stereo, 128x128 mono.

Gymnasium's ``CarRacing-v3`` (96x96 pixels, Box2D) is measured in the same run as
the baseline when Box2D is installed (``pip install box2d pygame``). Target: at
least 10x CarRacing's steps per second at 64x64 mono, on one core.

    python benchmarks/env_speed.py [--steps N]
"""

from __future__ import annotations

import argparse
import os
import time

import gymnasium as gym
import numpy as np

import saferace  # noqa: F401  - registers the tasks
from saferace.agents.pure_pursuit import PurePursuit
from saferace.eval.tables import markdown_table

TARGET_RATIO = 10.0


def saferace_steps_per_second(steps: int, physics_only: bool = False, **kwargs) -> float:
    """Steps per second of the pure-pursuit driver lapping ``technical`` (resets excluded)."""
    env = gym.make("saferace/CenterLine-v0", track="technical", max_laps=100, **kwargs)
    base = env.unwrapped
    obs, info = env.reset(seed=0)
    agent = PurePursuit.for_env(env)
    if physics_only:
        base._observation = lambda velocity: obs  # skip rendering; physics and bookkeeping remain
    elapsed = 0.0
    for _ in range(steps):
        action = agent.act(obs, info)
        start = time.perf_counter()
        new_obs, _, terminated, truncated, info = env.step(action)
        elapsed += time.perf_counter() - start
        obs = obs if physics_only else new_obs
        if terminated or truncated:
            obs, info = env.reset()
    env.close()
    return steps / elapsed


def car_racing_steps_per_second(steps: int) -> float | None:
    """Steps per second of CarRacing-v3 with a constant throttle, or None without Box2D."""
    try:
        env = gym.make("CarRacing-v3")
    except gym.error.DependencyNotInstalled:
        return None
    env.reset(seed=0)
    action = np.array([0.0, 0.3, 0.0], np.float32)
    elapsed = 0.0
    for _ in range(steps):
        start = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(action)
        elapsed += time.perf_counter() - start
        if terminated or truncated:
            env.reset()
    env.close()
    return steps / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args()
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core
    configs = {
        "physics only": dict(physics_only=True),
        "64x64 mono": dict(image_size=(64, 64)),
        "64x64 stereo": dict(image_size=(64, 64), stereo=True),
        "128x128 mono": dict(image_size=(128, 128)),
        "64x64 mono, 2 ms physics": dict(image_size=(64, 64), physics_dt_s=0.002),
    }
    car_racing = car_racing_steps_per_second(max(200, args.steps // 5))
    rows = []
    for label, kwargs in configs.items():
        rate = saferace_steps_per_second(args.steps, **kwargs)
        ratio = f"{rate / car_racing:.1f}x" if car_racing else "-"
        rows.append([label, rate, 1e3 / rate, ratio])
    if car_racing:
        rows.append(["CarRacing-v3 96x96 (baseline)", car_racing, 1e3 / car_racing, "1.0x"])
    print(markdown_table(["env", "steps/s", "ms/step", "vs CarRacing"], rows))
    if car_racing:
        mono = rows[1][1] / car_racing
        verdict = "met" if mono >= TARGET_RATIO else "MISSED"
        print(f"target: 64x64 mono >= {TARGET_RATIO:.0f}x CarRacing -> {mono:.1f}x, {verdict}")
    else:
        print("CarRacing-v3 not measured: install box2d and pygame for the baseline")


if __name__ == "__main__":
    main()
