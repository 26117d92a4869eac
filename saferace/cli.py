"""The ``saferace`` command line: ``saferace raceline TRACK ...``."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from saferace.errors import SafeRaceError


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``saferace`` console script."""
    parser = _parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s"
    )
    try:
        return args.command(args)
    except SafeRaceError as exc:
        print(f"saferace: error: {exc}", file=sys.stderr)
        return 2


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="saferace", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress")
    commands = parser.add_subparsers(required=True, metavar="COMMAND")

    raceline = commands.add_parser(
        "raceline", help="minimum-curvature racing line and speed profiles of a track"
    )
    raceline.add_argument("track", help="built-in track name or track CSV path")
    raceline.add_argument("--out", type=Path, help="write the racing line CSV here")
    raceline.add_argument(
        "--car-width-m", type=float, default=None, help="car width (default 0.30)"
    )
    raceline.add_argument(
        "--margin-m", type=float, default=None, help="extra clearance (default 0.10)"
    )
    raceline.add_argument(
        "--plot", type=Path, help="draw the track, both lines and speeds to a PNG"
    )
    raceline.set_defaults(command=_raceline)

    drive = commands.add_parser("drive", help="a driver laps a track; video and Rerun recording")
    _add_episode_arguments(drive, default_agent="pure-pursuit")
    drive.add_argument("--seed", type=int, default=0)
    drive.add_argument("--image-size", type=int, default=64, help="onboard image height and width")
    drive.add_argument("--stereo", action="store_true", help="stereo camera pair (6 channels)")
    drive.add_argument("--video", type=Path, help="write onboard + chase view MP4 here")
    drive.add_argument("--rerun", type=Path, help="write a Rerun recording (.rrd) here")
    drive.set_defaults(command=_drive)

    evaluate = commands.add_parser(
        "eval", help="evaluate an agent; one JSON row per (agent, task, track, seed)"
    )
    _add_episode_arguments(evaluate, default_agent="expert")
    evaluate.add_argument("--seeds", type=int, nargs="+", default=[0])
    evaluate.add_argument(
        "--model",
        default="dynamic",
        choices=["kinematic", "dynamic", "dynamic-paper"],
        help="vehicle model of the expert MPC",
    )
    evaluate.add_argument(
        "--out", type=Path, required=True, help="JSONL file to append the rows to"
    )
    evaluate.set_defaults(command=_eval)

    board = commands.add_parser("leaderboard", help="markdown table (and plots) from eval results")
    board.add_argument("results", type=Path, nargs="+", help="JSONL files written by saferace eval")
    board.add_argument("--csv", type=Path, help="also write the table as CSV")
    board.add_argument("--plot", type=Path, help="driven trajectories and speeds to a PNG")
    board.set_defaults(command=_leaderboard)

    sysid = commands.add_parser(
        "sysid", help="identify the vehicle-model parameters from MuJoCo runs"
    )
    sysid.add_argument(
        "--out", type=Path, default=None, help="parameter file (default: stored with the car)"
    )
    sysid.set_defaults(command=_sysid)

    shots = commands.add_parser("snapshots", help="PNGs of the onboard and chase views of tracks")
    shots.add_argument("--out", type=Path, default=Path("results/snapshots"))
    shots.add_argument("--tracks", nargs="*", help="track names or CSVs (default: all built-in)")
    shots.add_argument("--image-size", type=int, default=64)
    shots.set_defaults(command=_snapshots)
    return parser


TASKS = ("CenterLine", "RacingLine")


def _add_episode_arguments(parser: argparse.ArgumentParser, default_agent: str) -> None:
    """The arguments of one driven episode, shared by ``drive`` and ``eval``."""
    parser.add_argument("--task", default="RacingLine", choices=TASKS)
    parser.add_argument(
        "--track", default="technical", help="built-in track name or track CSV path"
    )
    parser.add_argument(
        "--agent", default=default_agent, help="expert, pure-pursuit or MODULE:FACTORY"
    )
    parser.add_argument("--laps", type=int, default=1)


def _raceline(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from saferace.eval.tables import markdown_table
    from saferace.track import Track, VehicleEnvelope
    from saferace.track.raceline import RacingLineSettings, center_line, racing_line

    envelope = VehicleEnvelope()
    if args.car_width_m is not None:
        if args.car_width_m <= 0:
            raise SafeRaceError(f"--car-width-m must be positive, got {args.car_width_m}")
        envelope = replace(envelope, width_m=args.car_width_m)
    settings = RacingLineSettings()
    if args.margin_m is not None:
        if args.margin_m < 0:
            raise SafeRaceError(f"--margin-m must not be negative, got {args.margin_m}")
        settings = replace(settings, margin_m=args.margin_m)

    track = Track.load(args.track, car_width_m=envelope.width_m)
    center = center_line(track, envelope, settings.step_m)
    racing = racing_line(track, envelope, settings)
    rows = [
        [
            line.name,
            line.length_m,
            line.curvature_squared_integral,
            line.lap_time_s,
            float(line.vx_mps.max()),
        ]
        for line in (center, racing)
    ]
    print(f"track {track.name}: {track.length_m:.2f} m, {track.point_count} points")
    print(
        markdown_table(
            ["line", "length [m]", "int kappa^2 ds [1/m]", "lap time [s]", "top speed [m/s]"], rows
        )
    )
    if args.out:
        racing.to_csv(args.out)
        print(f"racing line written to {args.out}")
    if args.plot:
        from saferace.eval.track_plots import plot_reference_lines

        plot_reference_lines(track, center, racing, args.plot)
        print(f"plot written to {args.plot}")
    return 0


def _drive(args: argparse.Namespace) -> int:
    from saferace.eval.drive import drive
    from saferace.eval.leaderboard import leaderboard_markdown
    from saferace.eval.runner import result_row

    _check_laps(args.laps)
    result = drive(
        args.task,
        args.track,
        agent=args.agent,
        laps=args.laps,
        video=args.video,
        rerun=args.rerun,
        seed=args.seed,
        image_size=(args.image_size, args.image_size),
        stereo=args.stereo,
    )
    row = result_row(
        args.agent, args.task, Path(args.track).stem, args.track, args.seed, args.laps, "-", result
    )
    print(leaderboard_markdown([row]))
    for label, path in (("video", args.video), ("rerun recording", args.rerun)):
        if path:
            print(f"{label} written to {path}")
    return 0 if result.summary["laps_completed"] == args.laps else 1


def _eval(args: argparse.Namespace) -> int:
    from saferace.eval.leaderboard import leaderboard_markdown
    from saferace.eval.runner import evaluate

    _check_laps(args.laps)
    rows = evaluate(
        args.agent,
        args.task,
        args.track,
        args.seeds,
        laps=args.laps,
        model=args.model,
        out=args.out,
    )
    print(leaderboard_markdown(rows))
    print(f"{len(rows)} rows appended to {args.out}")
    return 0


def _leaderboard(args: argparse.Namespace) -> int:
    from saferace.eval.leaderboard import (
        leaderboard_markdown,
        plot_trajectories,
        write_leaderboard_csv,
    )
    from saferace.eval.runner import read_jsonl

    rows = []
    for path in args.results:
        if not path.exists():
            raise SafeRaceError(
                f"no results file at {path}; write one with saferace eval --out {path}"
            )
        rows += read_jsonl(path)
    if not rows:
        raise SafeRaceError("the results files hold no rows")
    print(leaderboard_markdown(rows))
    if args.csv:
        write_leaderboard_csv(rows, args.csv)
        print(f"table written to {args.csv}")
    if args.plot:
        plot_trajectories(rows, args.plot)
        print(f"plot written to {args.plot}")
    return 0


def _check_laps(laps: int) -> None:
    if laps < 1:
        raise SafeRaceError(f"--laps must be at least 1, got {laps}")


def _snapshots(args: argparse.Namespace) -> int:
    from saferace.eval.drive import snapshots
    from saferace.track import builtin_track_names

    for path in snapshots(args.out, args.tracks or builtin_track_names(), args.image_size):
        print(path)
    return 0


def _sysid(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table
    from saferace.safety.vehicle_params import PARAMS_FILE
    from saferace.sysid.identify import identify

    result = identify()
    out = args.out or PARAMS_FILE
    result.params.to_json(out, extra=result.report())
    print(
        markdown_table(
            ["parameter", "value"], [[k, float(v)] for k, v in vars(result.params).items()]
        )
    )
    print()
    print(markdown_table(["fit residual", "RMS"], [[k, v] for k, v in result.residuals.items()]))
    print()
    rows = [
        [speed, model, errors["rms_e_y_m"], errors["rms_e_psi_rad"]]
        for speed, by_model in result.prediction.items()
        for model, errors in by_model.items()
    ]
    print("open-loop prediction error after 0.5 s (RMS over windows of the steering sweeps):")
    print(markdown_table(["speed", "model", "e_y [m]", "e_psi [rad]"], rows))
    print(f"parameters written to {out}")
    return 0
