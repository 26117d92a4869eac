"""The generic perception model on tracks and looks nothing was tuned on.

Tracks: random tracks by seed (default 6001-6004, none of the model's training or
calibration seeds) and a kidney-shaped track of our own (a limacon with a concave side,
0.84-1.16 m lane), written to ``--out``. Three parts, each a ``saferace robustness``
folder under ``--out`` (resumable):

- **coverage**: the expert drives a lap of every track at shift severity 0 behind the
  default filter (robust, fed the generic model): per track the share of steps whose
  truth lay in the interval, with its Clopper-Pearson band (target: at least 93% on every
  track) and the share the monitor raised on (target: at most 5%);
- **severities**: the drift, weave and speeding agents (and ``--learned CKPT@TRACK``: a
  learned driver on its own track) behind the default filter at severities 0-5 on the
  first random track and ours: completion and time outside (target: 0 s in every run;
  stopping is allowed as the look moves away);
- **against the truth**: at severity 0 the same agents behind the same filter fed the
  true state: each generic lap within 10% of its true-state lap.

    python benchmarks/generic_perception.py [--out DIR] [--seeds 6001 ...] [--learned CKPT@TRACK]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from saferace.eval.filter_config import FilterConfig
from saferace.eval.tables import markdown_table
from saferace.experiments.robustness import (
    TRACK_COLUMNS,
    RobustnessConfig,
    run_robustness,
    track_rows,
)
from saferace.learning.perception import ensure_perception_model
from saferace.names import GENERIC_SOURCE, ROBUST_GAINS, SHIFT_LOOKS
from saferace.track.random_track import write_random_tracks
from saferace.track.track_io import write_track_csv

RECKLESS = ("drift", "weave", "speeding")
COVERAGE_TARGET = 0.93
ALARM_TARGET = 0.05
LAP_TIME_TARGET = 1.10


def kidney_track(path: Path) -> str:
    """Our own track: a limacon stretched 1.2x, with a concave side and a lane that narrows
    from 1.16 to 0.84 m."""
    theta = np.linspace(0.0, 2.0 * np.pi, 400, endpoint=False)
    radius = 4.0 + 1.6 * np.cos(theta) + 0.5 * np.sin(2.0 * theta)
    half_width = 0.5 - 0.08 * np.cos(theta - 1.0)
    x, y = 1.2 * radius * np.cos(theta), radius * np.sin(theta)
    write_track_csv(path, x, y, half_width, half_width)
    return str(path)


def robustness(out: Path, agent: str, tracks: list[str], looks: tuple[str, ...], source: str):
    """The runs of ``agent`` on ``tracks`` in ``looks`` behind the default filter of a
    perceived state (robust, ``tuned`` gains) fed ``source`` (``oracle``: the truth, whose
    interval is a point)."""
    safety = FilterConfig(
        kind="cbf",
        state_source=None if source == "oracle" else source,
        uncertainty="robust",
        gains=ROBUST_GAINS,
    )
    config = RobustnessConfig(agent, "CenterLine", tuple(tracks), looks, (0,), safety=safety)
    name = f"{agent.partition(':')[0]}_{source.replace(':', '-')}_{len(looks)}looks"
    return run_robustness(config, out / name, progress=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/generic_perception"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[6001, 6002, 6003, 6004])
    parser.add_argument("--source", default=GENERIC_SOURCE, help="generic or generic:RECIPE")
    parser.add_argument("--learned", help="CKPT@TRACK: a learned driver on its own track")
    args = parser.parse_args()
    ensure_perception_model(args.source)
    tracks = [*write_random_tracks(args.out / "tracks", args.seeds)]
    tracks.append(kidney_track(args.out / "tracks" / "own_kidney.csv"))

    coverage_runs = robustness(args.out, "expert", tracks, ("severity-0",), args.source)
    rows = track_rows(coverage_runs, ("severity-0",))
    print("Coverage of the generic model's interval, the expert at severity 0:\n")
    print(markdown_table(TRACK_COLUMNS, rows))
    shares = [run["covered_steps"] / run["scored_steps"] for run in coverage_runs]
    alarms = [run["alarm_rate"] for run in coverage_runs]
    print(
        f"\nlowest coverage {100 * min(shares):.1f}% (target >= {100 * COVERAGE_TARGET:.0f}% on "
        f"every track: {'met' if min(shares) >= COVERAGE_TARGET else 'missed'}); highest alarm "
        f"rate {100 * max(alarms):.1f}% (target <= {100 * ALARM_TARGET:.0f}%: "
        f"{'met' if max(alarms) <= ALARM_TARGET else 'missed'})\n"
    )

    drivers = [(agent, [tracks[0], tracks[-1]]) for agent in RECKLESS]
    if args.learned:
        checkpoint, _, track = args.learned.partition("@")
        drivers.append((f"learned:{checkpoint}", [track]))
    sweep, against = [], []
    for agent, driven in drivers:
        runs = robustness(args.out, agent, driven, SHIFT_LOOKS, args.source)
        truth = robustness(args.out, agent, driven, ("severity-0",), "oracle")
        label = agent.partition(":")[0]
        for look in SHIFT_LOOKS:
            mine = [run for run in runs if run["look"] == look]
            sweep.append(
                [
                    label,
                    look,
                    len(mine),
                    f"{sum(run['laps_completed'] for run in mine)} of {len(mine)}",
                    100 * float(np.mean([run["completion"] for run in mine])),
                    max(run["time_outside_lane_s"] for run in mine),
                    100 * float(np.mean([run["alarm_rate"] for run in mine])),
                ]
            )
        for run in (run for run in runs if run["look"] == "severity-0"):
            (base,) = [other for other in truth if other["track"] == run["track"]]
            ratio = (
                run["lap_time_s"] / base["lap_time_s"]
                if run["lap_time_s"] and base["lap_time_s"]
                else None
            )
            against.append(
                [
                    label,
                    Path(run["track"]).stem,
                    run["lap_time_s"] or "-",
                    base["lap_time_s"] or "-",
                    "-" if ratio is None else f"{ratio:.3f}",
                    "-" if ratio is None else "yes" if ratio <= LAP_TIME_TARGET else "no",
                ]
            )
    columns = ["driver", "look", "runs", "laps", "completion [%]", "outside, worst [s]"]
    print("Behind the default filter at shift severities 0-5:\n")
    print(markdown_table([*columns, "alarms [%]"], sweep))
    outside = max(row[5] for row in sweep)
    print(f"\nworst time outside the lane over {len(sweep)} looks: {outside:.2f} s (target 0)\n")
    print("At severity 0, the generic model's lap against the true state's, same filter:\n")
    print(
        markdown_table(
            ["driver", "track", "lap, generic [s]", "lap, true state [s]", "ratio", "within 10%"],
            against,
        )
    )


if __name__ == "__main__":
    main()
