"""What a second car costs a step: the racing task at 64x64 mono with one car, and with an
opponent driven by pure pursuit (and, for scale, by the expert MPC), measured in turn.

Both cars are driven by pure pursuit. Only ``env.step`` is timed: with an ``external``
opponent (its actions given from outside, as the PettingZoo env gives them) that is the
second car's physics, contacts, state and image; with a built-in opponent it is its driver
too. Target: a two-car step with an external opponent at most 1.3x a one-car step.

    python benchmarks/traffic_speed.py [--steps N] [--repeats K] [--track NAME]
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

TARGET_RATIO = 1.3
SETUPS = {
    "one car": [],
    "external opponent": ["external:gap_m=3"],
    "pure-pursuit opponent": ["pure-pursuit:gap_m=3,lateral_offset_m=0"],
    "expert opponent": ["expert:gap_m=3"],
}


def step_time_ms(track: str, opponents: list[str], steps: int) -> float:
    """The mean time of ``env.step`` over ``steps`` steps after 20 warm-up steps (ms)."""
    env = gym.make("saferace/RacingLine-v0", track=track, opponents=opponents, max_laps=100)
    driver = PurePursuit.for_env(env)
    traffic = env.unwrapped.traffic
    observation, info = env.reset(seed=0)
    elapsed = 0.0
    for step in range(steps + 20):
        action = driver.act(observation, info)
        if traffic is not None and traffic.cars[0].policy is None:
            car = traffic.cars[0]
            traffic.set_external_actions({car.name: driver.act(None, car.state)})
        start = time.perf_counter()
        observation, _, terminated, truncated, info = env.step(action)
        if step >= 20:
            elapsed += time.perf_counter() - start
        if terminated or truncated:
            observation, info = env.reset()
    env.close()
    return 1e3 * elapsed / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--track", default="technical")
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    times: dict[str, list[float]] = {name: [] for name in SETUPS}
    for _ in range(args.repeats):  # in turn, so that the machine's load hits every setup
        for name, opponents in SETUPS.items():
            times[name].append(step_time_ms(args.track, opponents, args.steps))
    best = {name: min(values) for name, values in times.items()}
    rows = [[name, f"{best[name]:.2f}", f"{best[name] / best['one car']:.2f}"] for name in SETUPS]
    print(markdown_table(["setup", "step (ms, best of runs)", "vs one car"], rows))
    ratio = best["external opponent"] / best["one car"]
    verdict = "meets" if ratio <= TARGET_RATIO else "misses"
    print(f"\ntwo cars / one car = {ratio:.2f}: {verdict} the target of {TARGET_RATIO}x")
    spread = {name: f"{np.ptp(values):.2f}" for name, values in times.items()}
    print(f"spread between runs (ms): {spread}")


if __name__ == "__main__":
    main()
