"""Write the SafeRace benchmark suite: its evaluation tracks, the expert's lap times and the
traffic set.

The evaluation tracks are random tracks (``write_random_track``, 3 m radius, as the safety
table's) from seeds that nothing else in the repository uses; the expert MPC laps every
track, task and start of the protocol once, and its lap times are the suite's references
(the traffic set's runs are measured against the expert's racing-line laps alone).
Run once from the repository root (``python scripts/make_benchmark_suite.py``); changing
anything it writes means a new suite version (see ``saferace/experiments/benchmark.py``).
"""

from __future__ import annotations

import json

from saferace.eval.agents import make_agent
from saferace.eval.filters import FilterConfig
from saferace.eval.runner import make_task_env, max_steps_for, run_episode
from saferace.experiments.benchmark import SUITE_VERSION, suite_folder
from saferace.track import Track, builtin_track_names
from saferace.track.random_track import write_random_track

EVALUATION_TRACK_SEEDS = (901, 902)
TRACK_RADIUS_M = 3.0
PROTOCOL = {
    "tasks": ["CenterLine", "RacingLine"],
    "seeds": [0, 1],
    "start_fractions": [0.0, 0.5],
    "laps": 1,
    "max_seconds": 60.0,
    "filters": ["none", "cbf"],
}
TRAFFIC = {
    "task": "Overtake",
    "opponents": {
        "expert": ["expert:gap_m=2,speed_factor=0.8"],
        "braking": ["braking:gap_m=2,speed_factor=0.8"],
    },
    "seeds": [0],
    "laps": 2,
    "max_seconds": 60.0,
    "collision_factor": 0.6,
}


def expert_lap_time(track: str, task: str, seed: int, start_fraction: float) -> float:
    """The expert's lap time from ``start_fraction`` of the lap (raises if it fails)."""
    length = Track.load(track).length_m
    env = make_task_env(
        task,
        track,
        PROTOCOL["laps"],
        FilterConfig(),
        seed,
        max_steps=max_steps_for(PROTOCOL["max_seconds"]),
        start_s_m=start_fraction * length,
    )
    try:
        result = run_episode(env, make_agent("expert", env), seed=seed)
    finally:
        env.close()
    summary = result.summary
    if summary["laps_completed"] != 1 or summary["time_outside_lane_s"] > 0:
        raise RuntimeError(f"the expert did not lap {track} {task} from {start_fraction}")
    return summary["mean_lap_time_s"]


def main() -> None:
    folder = suite_folder(SUITE_VERSION)
    folder.mkdir(parents=True, exist_ok=True)
    tracks = list(builtin_track_names())
    for seed in EVALUATION_TRACK_SEEDS:
        name = f"eval_{seed}"
        write_random_track(folder / f"{name}.csv", seed, TRACK_RADIUS_M)
        tracks.append(name)
    references = {}
    for track in tracks:
        argument = str(folder / f"{track}.csv") if track.startswith("eval_") else track
        for task in PROTOCOL["tasks"]:
            for seed, fraction in zip(PROTOCOL["seeds"], PROTOCOL["start_fractions"], strict=True):
                lap = expert_lap_time(argument, task, seed, fraction)
                references[f"{track}/{task}/{seed}"] = round(lap, 4)
                print(f"{track:10s} {task:10s} start {fraction:.1f}: {lap:.2f} s")
    suite = {"version": SUITE_VERSION, "tracks": tracks, **PROTOCOL}
    suite["expert_lap_time_s"] = references
    suite["traffic"] = TRAFFIC
    (folder / "suite.json").write_text(json.dumps(suite, indent=2) + "\n")
    print(f"suite v{SUITE_VERSION} written to {folder}")


if __name__ == "__main__":
    main()
