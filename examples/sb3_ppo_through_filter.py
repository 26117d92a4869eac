"""Train a Stable-Baselines3 PPO agent from pixels on a SafeRace task, through the filter.

The shared safety filter wraps the task, so every action the agent explores is certified
before the car gets it (the paper's point: a learner that cannot yet drive stays in its
lane), and the agent sees the task's reward for the action that was applied. Actions are
rescaled to [-1, 1] outside the filter, which works in physical units. A few minutes on a
laptop CPU trains nothing that laps; the example shows how the pieces plug together.

    python examples/sb3_ppo_through_filter.py [--timesteps 20000] [--track lab] [--out DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import gymnasium as gym
from gymnasium.wrappers import RescaleAction

import saferace  # noqa: F401  - registers the tasks
from saferace.errors import SafeRaceError
from saferace.extras import require
from saferace.safety.cbf.filter import GAIN_PRESETS, SafetyFilter

try:  # Stable-Baselines3 is an extra: pip install 'saferace[sb3]'
    PPO = require("stable_baselines3", "sb3", "this example").PPO
    BaseCallback = require("stable_baselines3.common.callbacks", "sb3", "this example").BaseCallback
except SafeRaceError as error:
    sys.exit(f"error: {error}")


class FilterLog(BaseCallback):
    """Counts the filter's interventions and the steps outside the lane while training."""

    def __init__(self) -> None:
        super().__init__()
        self.steps = self.interventions = self.outside = 0

    def _on_step(self) -> bool:
        for info in self.locals["infos"]:
            self.steps += 1
            self.interventions += bool(info["safety"]["intervened"])
            self.outside += bool(info["outside_lane"])
        return True


def make_env(track: str, max_seconds: float) -> gym.Env:
    env = gym.make(
        "saferace/CenterLine-v0", track=track, image_size=(64, 64), max_steps=int(20 * max_seconds)
    )
    return RescaleAction(SafetyFilter(env, **GAIN_PRESETS["grip"]), -1.0, 1.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timesteps", type=int, default=20_000)
    parser.add_argument("--track", default="lab")
    parser.add_argument("--max-seconds", type=float, default=20.0, help="per training episode")
    parser.add_argument("--out", type=Path, default=Path("results/sb3"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    env = make_env(args.track, args.max_seconds)
    model = PPO("MultiInputPolicy", env, n_steps=256, batch_size=64, seed=args.seed, verbose=0)
    log = FilterLog()
    started = time.perf_counter()
    model.learn(total_timesteps=args.timesteps, callback=log, progress_bar=True)
    seconds = time.perf_counter() - started
    args.out.mkdir(parents=True, exist_ok=True)
    model.save(args.out / "ppo_saferace")
    print(
        f"trained {log.steps} steps in {seconds:.0f} s: the filter intervened in "
        f"{100 * log.interventions / max(log.steps, 1):.1f}% of them, the car was outside its "
        f"lane in {log.outside}"
    )

    observation, info = env.reset(seed=args.seed + 1)
    done, progress_m, outside = False, 0.0, 0
    while not done:
        action, _ = model.predict(observation, deterministic=True)
        observation, _, terminated, truncated, info = env.step(action)
        progress_m, outside = info["progress_m"], outside + bool(info["outside_lane"])
        done = terminated or truncated
    laps = info["lap"]
    print(
        f"evaluation: {progress_m:.1f} m driven ({laps} lap(s)), {outside} steps outside the "
        f"lane; model saved to {args.out / 'ppo_saferace.zip'}"
    )
    env.close()


if __name__ == "__main__":
    main()
