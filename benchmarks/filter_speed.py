"""The safety filter's QP solve time per control step, beside the cvxpy reference's.

The problems are the ones the filter met while a weaving reckless agent drove (true state;
20 noisy state samples with chance constraints; and the robust mode's rows, one per barrier
and corner or centre of the samples' interval). Each is solved by the filter's own
solver (``saferace.safety.cbf.qp``) and by the cvxpy formulation with Clarabel
(``saferace.safety.cbf.reference_qp``); the table gives the median and 95th percentile per
solve, cvxpy's both as wall time and as Clarabel's own solve time. Target: under 0.1 ms.

    python benchmarks/filter_speed.py [--track NAME] [--seconds S]
"""

from __future__ import annotations

import argparse
import time
import warnings

import gymnasium as gym
import numpy as np

import saferace  # noqa: F401  - registers the tasks
from saferace.agents.reckless import WeaveAgent
from saferace.eval.runner import run_episode
from saferace.eval.tables import markdown_table
from saferace.safety.cbf.filter import SafetyFilter
from saferace.safety.cbf.qp import solve_filter_qp
from saferace.safety.cbf.reference_qp import CLARABEL_TIGHT, filter_qp_problem
from saferace.safety.uncertainty.state_sources import NoisyOracleStateSource, OracleStateSource

TARGET_MS = 0.1
REPEATS = 20


def collect_problems(track: str, seconds: float, state_source, uncertainty: str) -> list:
    env = gym.make("saferace/CenterLine-v0", track=track, max_laps=3, max_steps=int(seconds * 20))
    env = SafetyFilter(env, state_source=state_source, uncertainty=uncertainty)
    problems = []

    def record(*_) -> None:
        problems.append(env.last_problem)

    run_episode(env, WeaveAgent.for_env(env), seed=0, on_step=record)
    env.close()
    return problems


def our_times_ms(problems: list) -> np.ndarray:
    """Per problem, the fastest of ``REPEATS`` solves (the machine's noise is one-sided)."""
    times = []
    for problem in problems:
        best = np.inf
        for _ in range(REPEATS):
            started = time.perf_counter()
            solve_filter_qp(problem)
            best = min(best, time.perf_counter() - started)
        times.append(best)
    return np.array(times) * 1e3


def cvxpy_times_ms(problems: list) -> tuple[np.ndarray, np.ndarray, float]:
    """Wall and Clarabel solve times, and the largest difference from our answer."""
    import cvxpy as cp

    wall, inner, worst = [], [], 0.0
    for problem in problems:
        program, u, _ = filter_qp_problem(problem)
        started = time.perf_counter()
        program.solve(solver=cp.CLARABEL, **CLARABEL_TIGHT)
        wall.append(time.perf_counter() - started)
        inner.append(program.solver_stats.solve_time)
        worst = max(worst, float(np.abs(np.asarray(u.value) - solve_filter_qp(problem).u).max()))
    return np.array(wall) * 1e3, np.array(inner) * 1e3, worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--track", default="technical")
    parser.add_argument("--seconds", type=float, default=20.0)
    args = parser.parse_args()
    warnings.filterwarnings("ignore", message="Solution may be inaccurate")  # tight tolerances
    rows = []
    for label, source, uncertainty in (
        ("true state", OracleStateSource(), "chance"),
        ("20 noisy samples (chance)", NoisyOracleStateSource(seed=0), "chance"),
        ("their interval's 9 points (robust)", NoisyOracleStateSource(seed=0), "robust"),
    ):
        problems = collect_problems(args.track, args.seconds, source, uncertainty)
        ours = our_times_ms(problems)
        wall, inner, worst = cvxpy_times_ms(problems)
        rows.append(
            [
                label,
                len(problems),
                float(np.median(ours)),
                float(np.percentile(ours, 95)),
                float(np.median(wall)),
                float(np.percentile(wall, 95)),
                float(np.median(inner)),
                f"{np.median(wall) / np.median(ours):.0f}x",
                f"{worst:.1e}",
            ]
        )
    print(
        markdown_table(
            [
                "problems",
                "count",
                "ours median [ms]",
                "ours p95 [ms]",
                "cvxpy median [ms]",
                "cvxpy p95 [ms]",
                "Clarabel only median [ms]",
                "cvxpy / ours",
                "max |u diff|",
            ],
            rows,
        )
    )
    print(f"target: ours under {TARGET_MS} ms per solve")


if __name__ == "__main__":
    main()
