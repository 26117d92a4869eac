"""How far the lane state carried by odometry and the map strays from the truth.

Each agent (the ``expert``; ``drift``, ``weave`` and ``speeding`` behind the CBF filter fed
the true state, so that they keep driving, swerving and braking) laps each track given
(default: random tracks 5151, 6262 and 7373, which nothing was tuned on) for up to
``--seconds``. Along every drive two things are measured:

- the one-step error of
  :func:`~saferace.safety.uncertainty.dead_reckoning.carried_states`: the true
  ``[e_y, e_psi]`` a step later against the truth carried by the step's odometry, per metre
  driven. With the car's arc length known the carrying is exact geometry, so this is the
  arithmetic's rounding (about 1e-9); the bound the set grows by,
  :data:`~saferace.safety.uncertainty.dead_reckoning.ERROR_PER_M`, is a real car's odometry;
- the carried set itself: from the truth every ``--window`` seconds, a zero-width box
  carried for that window as the filter carries it (growth included). It counts the steps
  where the truth left the set (the target: none) and the set's widths.

    python benchmarks/dead_reckoning_error.py [--tracks NAME|CSV ...] [--seconds 20] [--window 2]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import gymnasium as gym
import numpy as np

import saferace  # noqa: F401  (registers the tasks)
from saferace.eval.agents import act, make_agent
from saferace.eval.tables import markdown_table
from saferace.safety.cbf.filter import GAIN_PRESETS, SafetyFilter
from saferace.safety.decision import nominal_parts
from saferace.safety.uncertainty.dead_reckoning import (
    ERROR_PER_M,
    DeadReckoning,
    carried_states,
    centre_pose,
)
from saferace.track.odometry import odometry_step
from saferace.track.random_track import write_random_track

AGENTS = ("expert", "drift", "weave", "speeding")
RANDOM_TRACK_SEEDS = (5151, 6262, 7373)


def pose(info: dict) -> np.ndarray:
    return np.array([info["x_m"], info["y_m"], info["yaw_rad"]])


def drive(agent: str, track: str, seconds: float, window_s: float) -> dict:
    env = gym.make("saferace/CenterLine-v0", track=track, image_size=(16, 16))
    base = env.unwrapped
    if agent != "expert":
        env = SafetyFilter(env, **GAIN_PRESETS["grip"])
    centre = base.track.centerline
    driver = make_agent(agent, env, seed=0)
    observation, info = env.reset(seed=0)
    worst_per_m = np.zeros(2)
    window_steps = round(window_s / base.control_dt_s)
    box: DeadReckoning | None = None
    steps = outside = 0
    widths = []
    for step in range(round(seconds / base.control_dt_s)):
        truth = np.array([info["e_y_m"], info["e_psi_rad"]])
        before = info
        if step % window_steps == 0:
            box = DeadReckoning.trusted(truth, truth, pose(info), before["s_m"])
        action = nominal_parts(act(driver, observation, info))[0]
        observation, _, terminated, truncated, info = env.step(action)
        now = np.array([info["e_y_m"], info["e_psi_rad"]])
        odometry = odometry_step(pose(before), pose(info))
        centres = centre_pose(centre, before["s_m"]), centre_pose(centre, info["s_m"])
        carried = np.concatenate(carried_states(truth[:1], truth[1:], odometry, *centres))
        moved_m = float(np.hypot(*odometry[:2]))
        if moved_m > 1e-3:
            worst_per_m = np.maximum(worst_per_m, np.abs(now - carried) / moved_m)
        assert box is not None
        box = box.carried(pose(info), info["s_m"], centre)
        outside += bool(np.any(now < box.lower) or np.any(now > box.upper))
        widths.append(box.upper - box.lower)
        steps += 1
        if terminated or truncated:
            break
    env.close()
    return {
        "track": Path(track).stem,
        "agent": agent,
        "steps": steps,
        "worst_e_y_per_m": float(worst_per_m[0]),
        "worst_e_psi_per_m": float(worst_per_m[1]),
        "steps_outside_the_set": outside,
        "widest_set": np.max(widths, axis=0).tolist(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tracks", nargs="+", help="tracks (default: two random ones)")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--window", type=float, default=2.0, help="seconds carried per set")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        tracks = args.tracks or [
            str(write_random_track(Path(folder) / f"random_{seed}.csv", seed))
            for seed in RANDOM_TRACK_SEEDS
        ]
        rows = [drive(a, t, args.seconds, args.window) for t in tracks for a in AGENTS]
    print(
        markdown_table(
            [
                "track",
                "agent",
                "steps",
                "e_y error per m",
                "e_psi error per m",
                "steps outside the set",
                "widest set (m, rad)",
            ],
            [
                [
                    r["track"],
                    r["agent"],
                    r["steps"],
                    f"{r['worst_e_y_per_m']:.2e}",
                    f"{r['worst_e_psi_per_m']:.2e}",
                    r["steps_outside_the_set"],
                    f"{r['widest_set'][0]:.3f}, {r['widest_set'][1]:.3f}",
                ]
                for r in rows
            ],
        )
    )
    worst = np.max([[r["worst_e_y_per_m"], r["worst_e_psi_per_m"]] for r in rows], axis=0)
    total = sum(r["steps"] for r in rows)
    left = sum(r["steps_outside_the_set"] for r in rows)
    print(
        f"\n{total} steps: worst one-step error per metre {worst[0]:.2e} m, {worst[1]:.2e} "
        f"rad (the bound, a real car's odometry: {ERROR_PER_M[0]:g}, {ERROR_PER_M[1]:g}); "
        f"the truth left the carried set at {left} steps"
    )


if __name__ == "__main__":
    main()
