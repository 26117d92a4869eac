"""Measure every track CSV of a folder as a user's circuit: loading, racing line, driving.

For each ``*.csv`` that is a centre line (``x_m,y_m,w_tr_right_m,w_tr_left_m``): the points
the loader narrowed, the racing line's integral of kappa^2 ds against the one of a
``NAME_raceline.csv`` beside it (the F1TENTH collection's, made with TUM's tools; its share
of points outside our lane is given, since such a line cannot be driven), and the time the
racing line took. Unless ``--geometry-only``, also what ``saferace safety-table`` measures on
it (the expert's laps on both tasks, the reckless agents with and without the filter, oracle
and noisy), resumable in ``--out``; ``--expert-only`` drives only the expert, unfiltered,
one lap of each task per circuit (every circuit as given must load and be lapped).
``--smooth-rms-m`` measures the circuits with their centre lines smoothed (``Track.load``'s
option); the lanes as loaded are written to a folder of ``--out`` named by the smoothing,
and driven.

    python benchmarks/real_tracks.py ../shared/tracks/f1tenth [--geometry-only | --expert-only]
        [--smooth-rms-m 0.08 [--smooth-keeps widths|boundaries]] [--out DIR]
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

from saferace.eval.runner import evaluate
from saferace.eval.tables import markdown_table
from saferace.experiments.safety_table import filter_label, run_table
from saferace.names import DEFAULT_GAINS, TASKS
from saferace.track import Track, VehicleEnvelope
from saferace.track.raceline import RacingLineSettings, racing_line
from saferace.track.smoothing import SMOOTHING_KEEPS

RACELINE_SUFFIX = "_raceline"
GEOMETRY_COLUMNS = (
    "track",
    "length [m]",
    "points narrowed",
    "most narrowed [m]",
    "int kappa^2 ours [1/m]",
    "int kappa^2 collection's [1/m]",
    "ours / collection's",
    "collection's points outside our lane",
    "racing line [s]",
)


def collection_line(path: Path) -> np.ndarray | None:
    """``x, y, kappa`` and ``s`` of the ``NAME_raceline.csv`` beside a centre line, if any."""
    stem = path.stem.removesuffix("_centerline")
    candidate = path.with_name(f"{stem}{RACELINE_SUFFIX}.csv")
    if not candidate.exists():
        return None
    return np.genfromtxt(candidate, delimiter=";", comments="#")


def curvature_integral(line: np.ndarray) -> float:
    """Trapezoidal integral of kappa^2 ds of a collection racing line (closed)."""
    s, kappa = line[:, 0], line[:, 4]
    ds = np.diff(s)
    return float(np.sum(0.5 * (kappa[1:] ** 2 + kappa[:-1] ** 2) * ds))


def points_outside(track: Track, line: np.ndarray, clearance_m: float) -> int:
    """Points of a line farther out than the lane minus ``clearance_m`` (our racing line's
    bounds), by their Frenet offset from the centre line."""
    projector = track.projector()
    outside = 0
    for x, y in line[:, 1:3]:
        s, e_y = projector.project(float(x), float(y))
        w_right, w_left = track.widths(s)
        outside += bool(e_y > w_left - clearance_m or e_y < -(w_right - clearance_m))
    return outside


def geometry_row(path: Path, track: Track) -> list:
    settings = RacingLineSettings()
    started = time.perf_counter()
    ours = racing_line(track, settings=settings).curvature_squared_integral
    seconds = time.perf_counter() - started
    reference = collection_line(path)
    if reference is None:
        theirs = ratio = outside = "-"
    else:
        theirs = curvature_integral(reference)
        ratio = ours / theirs
        clearance = 0.5 * VehicleEnvelope().width_m + settings.margin_m
        outside = f"{points_outside(track, reference, clearance)} of {len(reference)}"
    narrowing = track.narrowing
    return [
        track.name,
        track.length_m,
        narrowing.points,
        narrowing.max_m,
        ours,
        theirs,
        ratio,
        outside,
        seconds,
    ]


def driving_rows(rows: list[dict]) -> list[list]:
    """Per track: the expert's laps and time outside, the reckless agents' time outside."""
    lines = []
    for track in dict.fromkeys(row["track"] for row in rows):
        mine = [row for row in rows if row["track"] == track]
        expert = {
            row["task"]: row["summary"]
            for row in mine
            if row["agent"] == "expert" and filter_label(row) == "none"
        }
        reckless = {
            label: sum(
                row["summary"]["time_outside_lane_s"]
                for row in mine
                if row["agent"] != "expert" and filter_label(row) == label
            )
            for label in ("none", "oracle", "noisy-prob")
        }
        lines.append(
            [
                track,
                *(expert[task]["mean_lap_time_s"] or "-" for task in ("CenterLine", "RacingLine")),
                sum(summary["time_outside_lane_s"] for summary in expert.values()),
                *reckless.values(),
            ]
        )
    return lines


def expert_rows(tracks: list[Path]) -> list[list]:
    """Per circuit: the expert's lap on both tasks without a filter ('-': it did not
    finish one) and its time outside the lane."""
    lines = []
    for path in tracks:
        laps, outside = [], 0.0
        for task in TASKS:
            (row,) = evaluate("expert", task, str(path), [0], progress=False)
            laps.append(row["summary"]["best_lap_time_s"] or "-")
            outside += row["summary"]["time_outside_lane_s"]
        lines.append([path.stem, *laps, outside])
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="a folder of track CSVs")
    parser.add_argument("--out", type=Path, default=Path("results/real_tracks"))
    modes = parser.add_mutually_exclusive_group()
    modes.add_argument("--geometry-only", action="store_true", help="load and racing line only")
    modes.add_argument(
        "--expert-only", action="store_true", help="and the expert's laps, without the table"
    )
    parser.add_argument(
        "--smooth-rms-m",
        type=float,
        default=None,
        help="smooth each centre line by this RMS distance (Track.load's smooth_rms_m)",
    )
    parser.add_argument(
        "--smooth-keeps",
        choices=SMOOTHING_KEEPS,
        default="widths",
        help="what a smoothed lane keeps: the given widths or boundaries (Track.load's)",
    )
    parser.add_argument(
        "--gains",
        default=DEFAULT_GAINS,
        help="the filter's settings (safety-table's --filter-gains)",
    )
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    tracks = sorted(
        path for path in args.folder.glob("*.csv") if not path.stem.endswith(RACELINE_SUFFIX)
    )
    if not tracks:
        parser.error(f"{args.folder} holds no track CSV")
    loaded = {
        path: Track.load(path, smooth_rms_m=args.smooth_rms_m, smooth_keeps=args.smooth_keeps)
        for path in tracks
    }
    print(markdown_table(GEOMETRY_COLUMNS, [geometry_row(*item) for item in loaded.items()]))
    if args.geometry_only:
        return
    if args.expert_only:
        columns = ("track", *(f"expert {task} lap [s]" for task in TASKS), "outside [s]")
        print(markdown_table(columns, expert_rows(tracks)))
        return
    if args.smooth_rms_m is not None:
        folder = args.out / f"tracks_smoothed_{args.smooth_rms_m}m_keeping_{args.smooth_keeps}"
        folder.mkdir(parents=True, exist_ok=True)
        tracks = [folder / path.name for path in tracks]
        for path, track in zip(tracks, loaded.values(), strict=True):
            track.to_csv(path)
    rows = run_table([str(path) for path in tracks], args.out, laps=1, max_seconds=120.0,
                     gains=args.gains)  # fmt: skip
    print(
        markdown_table(
            (
                "track",
                "expert CenterLine lap [s]",
                "expert RacingLine lap [s]",
                "expert outside [s]",
                "reckless outside, no filter [s]",
                "reckless outside, oracle filter [s]",
                "reckless outside, noisy filter [s]",
            ),
            driving_rows(rows),
        )
    )
    print(f"every run in {args.out / 'runs.jsonl'}, the safety table beside it")


if __name__ == "__main__":
    main()
