"""Write the safety filters' protocol (``saferace/assets/benchmark/filters/v1/suite.json``).

Its tracks are the drivers' benchmark's (v2): the four built-in ones and its two evaluation
tracks, copied beside it, with the expert's racing-line lap times v2 measured from the
start line. Its circuits are F1TENTH racetracks as given, which the repository does not
ship: the suite pins each centre line's sha256, and the expert MPC laps each once here for
its reference. Run once from the repository root::

    python scripts/make_filter_suite.py --circuits ../shared/tracks/f1tenth

Changing anything it writes means a new protocol version (see
``saferace/experiments/filter_suite.py``).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from saferace.eval.agents import make_agent
from saferace.eval.filters import FilterConfig
from saferace.eval.runner import file_sha256, make_task_env, max_steps_for, run_episode
from saferace.experiments.benchmark import load_suite
from saferace.experiments.filter_suite import FILTER_SUITE_VERSION, filter_suite_folder

TASK = "RacingLine"
CIRCUITS = ("BrandsHatch_centerline", "Monza_centerline", "Spielberg_centerline")
PROTOCOL = {
    "drivers": ["drift", "weave", "speeding", "expert"],
    "task": TASK,
    "seed": 0,
    "laps": 1,
    "max_seconds": 30.0,
    "conditions": {
        "true": {"state": "true"},
        "noisy": {"state": "noisy", "noise": [0.05, 0.05]},
        "perceived-0": {"state": "perceived", "look": 0},
        "perceived-2": {"state": "perceived", "look": 2},
        "perceived-4": {"state": "perceived", "look": 4},
        "perceived-0-late": {
            "state": "perceived",
            "look": 0,
            "faults": ["latency:severity=2,start=3,duration=inf,steps=2,random=0"],
        },
        "perceived-0-blackout": {
            "state": "perceived",
            "look": 0,
            "faults": ["blackout:severity=2,start=3,duration=1"],
        },
    },
    "traffic": {
        "task": "Overtake",
        "opponents": {"braking": ["braking:gap_m=2,speed_factor=0.8"]},
        "conditions": ["true", "perceived-0"],
    },
    "collision_factor": 0.6,
    "correction_scales": [0.36, 4.0],
}


def expert_lap_time(track: str) -> float:
    """The expert's racing-line lap of ``track`` from its start line (raises if it fails)."""
    env = make_task_env(TASK, track, 1, FilterConfig(), 0, max_steps=max_steps_for(400.0))
    try:
        summary = run_episode(env, make_agent("expert", env), seed=0).summary
    finally:
        env.close()
    if summary["laps_completed"] != 1 or summary["time_outside_lane_s"] > 0:
        raise RuntimeError(f"the expert did not lap {track}")
    return round(summary["mean_lap_time_s"], 4)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--circuits", type=Path, required=True, help="F1TENTH centre lines")
    args = parser.parse_args()
    drivers_suite = load_suite(2)
    folder = filter_suite_folder(FILTER_SUITE_VERSION)
    folder.mkdir(parents=True, exist_ok=True)
    for track in drivers_suite.tracks:
        own = drivers_suite.folder / f"{track}.csv"
        if own.exists():
            shutil.copyfile(own, folder / own.name)
    lap_times_s = drivers_suite.expert_lap_time_s
    references = {track: lap_times_s[f"{track}/{TASK}/0"] for track in drivers_suite.tracks}
    paths = {name: args.circuits / f"{name}.csv" for name in CIRCUITS}
    references.update({name: expert_lap_time(str(path)) for name, path in paths.items()})
    suite = {
        "version": FILTER_SUITE_VERSION,
        **PROTOCOL,
        "tracks": list(drivers_suite.tracks),
        "circuits": {
            "sha256": {name: file_sha256(path) for name, path in paths.items()},
            "conditions": ["true", "perceived-0"],
        },
        "expert_lap_time_s": references,
    }
    (folder / "suite.json").write_text(json.dumps(suite, indent=1) + "\n")


if __name__ == "__main__":
    main()
