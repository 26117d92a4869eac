"""The expert in traffic passing a slower car, without the filter, from several starts.

Each run: `Overtake-v0` (2 m behind one opponent at 80% of the racing line's speed: the
expert MPC on the racing line, blind to other cars; the ``racer``, the expert in traffic,
which leaves room to a car alongside; or the car that brakes hard at seeded intervals),
two laps, `terminate_on_collision=False`, seed 0, started at ``--starts`` even fractions
of the lap, on each track given (default: the built-in ones, random tracks 4242, 9137,
777, 2468 and 5151, and the benchmark's two evaluation tracks). It prints, per track and
opponent, the runs in which the ego got 0.5 m ahead of the opponent, the collisions the
ego caused and those the opponent caused, the time outside the lane and the runs that
finished. Target: no collision the ego causes; a pass wherever the lane leaves room for
one.

    python benchmarks/overtaking.py [--tracks NAME|CSV ...] [--opponents NAME ...]
                                    [--starts N] [--workers N] [--out rows.jsonl]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import tempfile
from multiprocessing import Pool
from pathlib import Path

import numpy as np
from tqdm import tqdm

from saferace.eval.tables import markdown_table
from saferace.experiments.benchmark import suite_folder
from saferace.track import builtin_track_names
from saferace.track.random_track import write_random_track

OPPONENTS = {
    "expert": "expert:gap_m=2,speed_factor=0.8",
    "racer": "racer:gap_m=2,speed_factor=0.8",
    "braking": "braking:gap_m=2,speed_factor=0.8",
}
RANDOM_TRACK_SEEDS = (4242, 9137, 777, 2468, 5151)
LAPS, MAX_SECONDS = 2, 120.0
#: The ego has passed once it leads the opponent by this much (m; ``ego_lead_m``).
PASSED_LEAD_M = 0.5


def run(job: tuple[str, str, int, int]) -> dict:
    """One run's row: when it passed, what it and the opponent caused, the lane, the laps."""
    from saferace.eval.agents import make_agent
    from saferace.eval.filters import FilterConfig
    from saferace.eval.runner import make_task_env, max_steps_for, run_episode
    from saferace.track import Track

    track, opponent, start, starts = job
    env = make_task_env(
        "Overtake",
        track,
        LAPS,
        FilterConfig(),
        seed=0,
        opponents=[OPPONENTS[opponent]],
        max_steps=max_steps_for(MAX_SECONDS),
        terminate_on_collision=False,
        start_s_m=Track.load(track).length_m * start / starts,
    )
    result = run_episode(env, make_agent("expert", env), seed=0)
    env.close()
    lead_m = np.asarray(result.steps["opponents_lead_m"], dtype=float)[:, 0]
    ahead = np.flatnonzero(lead_m > PASSED_LEAD_M)
    summary = result.summary
    return {
        "track": Path(track).stem,
        "opponent": opponent,
        "start": start,
        "passed_s": float(result.steps["time_s"][ahead[0]]) if len(ahead) else None,
        "ego_caused": summary["at_fault_collisions"],
        "opponent_caused": summary["collisions"] - summary["at_fault_collisions"],
        "outside_lane_s": summary["time_outside_lane_s"],
        "finished": summary["laps_completed"] >= LAPS,
    }


def summary(rows: list[dict]) -> str:
    """A markdown table of the rows by track and opponent."""
    table = []
    keys = dict.fromkeys((r["track"], r["opponent"]) for r in rows)
    for track, opponent in keys:
        group = [r for r in rows if (r["track"], r["opponent"]) == (track, opponent)]
        passes = [r["passed_s"] for r in group if r["passed_s"] is not None]
        table.append(
            [
                track,
                opponent,
                f"{len(passes)} of {len(group)}",
                f"{np.median(passes):.1f} s" if passes else "-",
                str(sum(r["ego_caused"] for r in group)),
                str(sum(r["opponent_caused"] for r in group)),
                f"{sum(r['outside_lane_s'] for r in group):.1f} s",
                str(sum(r["finished"] for r in group)),
            ]
        )
    header = ["track", "opponent", "passed", "median time to pass", "ego caused",
              "opponent caused", "outside the lane", "finished"]  # fmt: skip
    return markdown_table(header, table)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tracks", nargs="+", help="built-in names or CSVs")
    parser.add_argument("--opponents", nargs="+", choices=list(OPPONENTS), default=list(OPPONENTS))
    parser.add_argument("--starts", type=int, default=5, help="starts per track and opponent")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, help="also write the rows as JSONL")
    args = parser.parse_args()
    if args.starts < 1:
        parser.error("--starts must be at least 1")
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    with tempfile.TemporaryDirectory() as folder:
        tracks = args.tracks or [
            *builtin_track_names(),
            *(
                str(write_random_track(Path(folder) / f"random_{seed}.csv", seed))
                for seed in RANDOM_TRACK_SEEDS
            ),
            *(str(path) for path in sorted(suite_folder().glob("eval_*.csv"))),
        ]
        jobs = [
            (track, opponent, start, args.starts)
            for track, opponent, start in itertools.product(
                tracks, args.opponents, range(args.starts)
            )
        ]
        with Pool(args.workers) as pool:
            rows = list(tqdm(pool.imap(run, jobs), total=len(jobs), desc="runs"))
    if args.out:
        args.out.write_text("".join(json.dumps(row) + "\n" for row in rows))
    print(summary(rows))
    caused = [r for r in rows if r["ego_caused"]]
    print(f"\nruns with a collision the ego caused: {len(caused)} of {len(rows)}")
    for row in caused:
        print(f"  {row}")


if __name__ == "__main__":
    main()
