"""The expert MPC's time per control step: OSQP solve (median, 95th percentile) and the rest.

Targets at a horizon of 20: the solve under 5 ms, and the whole step of the dynamic model at
most 1 ms. The rest of a step (linearising and discretising 20 stages, one batched matrix
exponential, building the QP's vectors) is measured in the same run, as the share of the
step spent outside the solver.

    python benchmarks/mpc_speed.py [--track NAME] [--laps N]
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import saferace  # noqa: F401  - registers the tasks
from saferace.agents.mpc import MPCExpert, MPCSettings
from saferace.eval.runner import run_episode
from saferace.eval.tables import markdown_table

TARGET_MS = 5.0
STEP_TARGET_MS = 1.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--track", default="technical")
    parser.add_argument("--laps", type=int, default=2)
    args = parser.parse_args()
    rows = []
    for model in ("kinematic", "dynamic"):
        for horizon in (10, 20, 30):
            env = gym.make("saferace/RacingLine-v0", track=args.track, max_laps=args.laps)
            expert = MPCExpert.for_env(env, model=model, settings=MPCSettings(horizon=horizon))
            result = run_episode(env, expert, seed=0)
            env.close()
            solve = np.asarray(expert.stats.solve_times_s) * 1e3
            step = np.asarray(expert.stats.step_times_s) * 1e3
            outside = 1.0 - solve.sum() / step.sum()
            rows.append(
                [
                    model,
                    horizon,
                    float(np.median(solve)),
                    float(np.percentile(solve, 95)),
                    float(np.median(step)),
                    f"{100 * outside:.0f} %",
                    result.summary["laps_completed"],
                    expert.stats.failures,
                ]
            )
    print(
        markdown_table(
            [
                "model",
                "N",
                "solve median [ms]",
                "solve p95 [ms]",
                "step median [ms]",
                "outside solver",
                "laps",
                "failed solves",
            ],
            rows,
        )
    )
    worst = max(row[3] for row in rows if row[1] == 20)
    print(
        f"target: solve p95 under {TARGET_MS:.0f} ms at N = 20 -> {worst:.2f} ms, "
        f"{'met' if worst < TARGET_MS else 'MISSED'}"
    )
    [dynamic_step] = [row[4] for row in rows if row[:2] == ["dynamic", 20]]
    print(
        f"target: dynamic-model step median at most {STEP_TARGET_MS:.0f} ms at N = 20 -> "
        f"{dynamic_step:.2f} ms, {'met' if dynamic_step <= STEP_TARGET_MS else 'MISSED'}"
    )


if __name__ == "__main__":
    main()
