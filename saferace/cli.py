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
    _add_filter_arguments(evaluate)
    evaluate.add_argument(
        "--max-seconds", type=float, help="end an episode after this much simulated time"
    )
    evaluate.set_defaults(command=_eval)

    table = commands.add_parser(
        "safety-table",
        help="reckless agents and the expert with and without the safety filter, as a table",
    )
    table.add_argument("--tracks", nargs="*", help="track names or CSVs (default: all built-in)")
    table.add_argument(
        "--random-tracks",
        type=int,
        nargs="*",
        default=[],
        metavar="SEED",
        help="also generate random tracks with these seeds (written to OUT/tracks)",
    )
    table.add_argument("--out", type=Path, default=Path("results/safety"))
    table.add_argument("--laps", type=int, default=3)
    table.add_argument("--max-seconds", type=float, default=60.0)
    table.add_argument(
        "--state-noise", type=float, nargs=2, default=[0.05, 0.05], metavar=("E_Y_M", "E_PSI_RAD")
    )
    table.add_argument("--samples", type=int, default=20)
    table.add_argument("--filter-model", default="kinematic", choices=FILTER_MODELS)
    _add_gains_argument(table)
    table.set_defaults(command=_safety_table)

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
        "--agent",
        default=default_agent,
        help="expert, pure-pursuit, drift, weave, speeding or MODULE:FACTORY",
    )
    parser.add_argument("--laps", type=int, default=1)


FILTER_MODELS = ("kinematic", "dynamic", "dynamic-paper")
FILTER_GAINS = ("paper", "tuned")  # the keys of saferace.safety.filter.GAIN_PRESETS


def _add_filter_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--filter", default="none", choices=["none", "cbf"], help="wrap the agent in a filter"
    )
    parser.add_argument(
        "--filter-model", default="kinematic", choices=FILTER_MODELS, help="the filter's model"
    )
    parser.add_argument(
        "--state-noise",
        type=float,
        nargs=2,
        metavar=("E_Y_M", "E_PSI_RAD"),
        help="the filter sees noisy state samples with these standard deviations",
    )
    parser.add_argument("--samples", type=int, default=20, help="state samples per step")
    parser.add_argument(
        "--deterministic",
        action="store_true",
        help="filter on the samples' mean instead of with chance constraints",
    )
    _add_gains_argument(parser)


def _add_gains_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--filter-gains",
        default="paper",
        choices=FILTER_GAINS,
        help="the filter's class-K gains: the paper's, or those measured to cost the expert least",
    )


def _filter_config(args: argparse.Namespace):
    from saferace.eval.filters import FilterConfig

    if args.samples < 2:
        raise SafeRaceError(f"--samples must be at least 2, got {args.samples}")
    if args.state_noise is not None and min(args.state_noise) < 0:
        raise SafeRaceError(f"--state-noise must not be negative, got {args.state_noise}")
    if args.filter == "none" and (args.state_noise is not None or args.deterministic):
        raise SafeRaceError("--state-noise and --deterministic need --filter cbf")
    return FilterConfig(
        kind=args.filter,
        model=args.filter_model,
        state_noise=None if args.state_noise is None else tuple(args.state_noise),
        samples=args.samples,
        probabilistic=not args.deterministic,
        gains=args.filter_gains,
    )


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
    env_kwargs = {}
    if args.max_seconds is not None:
        if args.max_seconds <= 0:
            raise SafeRaceError(f"--max-seconds must be positive, got {args.max_seconds}")
        env_kwargs["max_steps"] = round(args.max_seconds * 20.0)
    rows = evaluate(
        args.agent,
        args.task,
        args.track,
        args.seeds,
        laps=args.laps,
        model=args.model,
        out=args.out,
        env_kwargs=env_kwargs,
        safety=_filter_config(args),
    )
    print(leaderboard_markdown(rows))
    print(f"{len(rows)} rows appended to {args.out}")
    return 0


def _safety_table(args: argparse.Namespace) -> int:
    from saferace.eval.safety_table import RANDOM_TRACK_RADIUS_M, run_table
    from saferace.track import builtin_track_names
    from saferace.track.random_track import write_random_track

    _check_laps(args.laps)
    if args.max_seconds <= 0 or args.samples < 2 or min(args.state_noise) < 0:
        raise SafeRaceError("need --max-seconds > 0, --samples >= 2, --state-noise >= 0")
    tracks = list(args.tracks) if args.tracks else list(builtin_track_names())
    for seed in args.random_tracks:
        path = args.out / "tracks" / f"random_{seed}.csv"
        write_random_track(path, seed, RANDOM_TRACK_RADIUS_M)
        tracks.append(str(path))
    run_table(
        tracks,
        args.out,
        laps=args.laps,
        max_seconds=args.max_seconds,
        noise=tuple(args.state_noise),
        samples=args.samples,
        model=args.filter_model,
        gains=args.filter_gains,
    )
    print((args.out / "safety_table.md").read_text())
    print(f"tables, runs and reckless_paths.png written to {args.out}")
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
