"""Reckless agents and the expert in traffic, behind the CBF filter and without it.

Each run: one agent (``drift``, ``weave``, ``speeding``, ``expert``) on the racing-line task
with one opponent 3 m ahead (``expert`` and ``racer`` at 80% of the racing line's speed,
``pure-pursuit`` on the centre line and ``lane-changer`` and ``blocker`` at 60%, ``braking``
at 80%), two laps or 80 s, seed 0, on each track given (default: the built-in ones and random tracks
4242 and 9137). It prints, per opponent and per agent, the runs with a collision the ego
caused, the collisions the opponent caused, the time outside the lane and the runs that
finished, and lists every filtered run that collided or left the lane. Target: behind the
filter, no collision the ego causes and no time outside the lane.

    python benchmarks/traffic_safety.py [--tracks NAME|CSV ...] [--workers N] [--out rows.jsonl]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import tempfile
from multiprocessing import Pool
from pathlib import Path

from tqdm import tqdm

from saferace.eval.tables import markdown_table
from saferace.track import builtin_track_names
from saferace.track.random_track import write_random_track

AGENTS = ("drift", "weave", "speeding", "expert")
OPPONENTS = {
    "expert": "expert:gap_m=3,speed_factor=0.8",
    "racer": "racer:gap_m=3,speed_factor=0.8",
    "pure-pursuit": "pure-pursuit:gap_m=3,speed_factor=0.6,lateral_offset_m=0",
    "lane-changer": "lane-changer:gap_m=3,speed_factor=0.6",
    "blocker": "blocker:gap_m=3,speed_factor=0.6",
    "braking": "braking:gap_m=3,speed_factor=0.8",
}
RANDOM_TRACK_SEEDS = (4242, 9137)
LAPS, MAX_SECONDS = 2, 80.0


def run(job: tuple[str, str, str, bool]) -> dict:
    """One run's row: what the ego caused, what the opponent caused, the lane, the laps."""
    from saferace.eval.agents import make_agent
    from saferace.eval.filters import FilterConfig
    from saferace.eval.runner import make_task_env, max_steps_for, run_episode

    track, agent_name, opponent, filtered = job
    env = make_task_env(
        "RacingLine",
        track,
        LAPS,
        FilterConfig(kind="cbf", gains="grip") if filtered else FilterConfig(),
        seed=0,
        opponents=[OPPONENTS[opponent]],
        max_steps=max_steps_for(MAX_SECONDS),
    )
    episode = run_episode(env, make_agent(agent_name, env), seed=0).summary
    env.close()
    return {
        "track": Path(track).stem,
        "agent": agent_name,
        "opponent": opponent,
        "filter": filtered,
        "ego_caused": episode["at_fault_collisions"],
        "opponent_caused": episode["collisions"] - episode["at_fault_collisions"],
        "outside_lane_s": episode["time_outside_lane_s"],
        "finished": episode["laps_completed"] >= LAPS,
    }


def summary(rows: list[dict], key: str, values) -> str:
    """A markdown table of the rows grouped by ``key`` (each of ``values``) and filter."""
    table = []
    for value, filtered in itertools.product(values, (True, False)):
        group = [r for r in rows if r[key] == value and r["filter"] == filtered]
        caused = [r["ego_caused"] for r in group]
        table.append(
            [
                value,
                "CBF" if filtered else "none",
                str(len(group)),
                f"{sum(c > 0 for c in caused)} ({sum(caused)})",
                str(sum(r["opponent_caused"] for r in group)),
                f"{sum(r['outside_lane_s'] > 0 for r in group)} "
                f"({sum(r['outside_lane_s'] for r in group):.1f} s)",
                str(sum(r["finished"] for r in group)),
            ]
        )
    header = [key, "filter", "runs", "ego caused (collisions)", "opponent caused",
              "left the lane (time)", "finished"]  # fmt: skip
    return markdown_table(header, table)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tracks", nargs="+", help="built-in names or CSVs")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, help="also write the rows as JSONL")
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    with tempfile.TemporaryDirectory() as folder:
        tracks = args.tracks or [
            *builtin_track_names(),
            *(
                str(write_random_track(Path(folder) / f"random_{seed}.csv", seed))
                for seed in RANDOM_TRACK_SEEDS
            ),
        ]
        jobs = list(itertools.product(tracks, AGENTS, OPPONENTS, (True, False)))
        with Pool(args.workers) as pool:
            rows = list(tqdm(pool.imap(run, jobs), total=len(jobs), desc="runs"))
    if args.out:
        args.out.write_text("".join(json.dumps(row) + "\n" for row in rows))
    print(summary(rows, "opponent", OPPONENTS))
    print()
    print(summary(rows, "agent", AGENTS))
    failures = [r for r in rows if r["filter"] and (r["ego_caused"] or r["outside_lane_s"])]
    print(
        f"\nfiltered runs with a collision the ego caused or time outside the lane: {len(failures)}"
    )
    for row in failures:
        print(f"  {row}")


if __name__ == "__main__":
    main()
