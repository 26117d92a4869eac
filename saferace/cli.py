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

    drive = commands.add_parser("drive", help="pure pursuit drives laps; video and Rerun recording")
    drive.add_argument("--task", default="RacingLine", choices=["CenterLine", "RacingLine"])
    drive.add_argument("--track", default="technical", help="built-in track name or track CSV path")
    drive.add_argument("--laps", type=int, default=1)
    drive.add_argument("--seed", type=int, default=0)
    drive.add_argument("--image-size", type=int, default=64, help="onboard image height and width")
    drive.add_argument("--stereo", action="store_true", help="stereo camera pair (6 channels)")
    drive.add_argument("--video", type=Path, help="write onboard + chase view MP4 here")
    drive.add_argument("--rerun", type=Path, help="write a Rerun recording (.rrd) here")
    drive.set_defaults(command=_drive)

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
    from saferace.eval.drive import drive, format_lap_times
    from saferace.eval.tables import markdown_table

    if args.laps < 1:
        raise SafeRaceError(f"--laps must be at least 1, got {args.laps}")
    summary = drive(
        args.task,
        args.track,
        laps=args.laps,
        video=args.video,
        rerun=args.rerun,
        seed=args.seed,
        image_size=(args.image_size, args.image_size),
        stereo=args.stereo,
    )
    print(
        markdown_table(
            [
                "task",
                "track",
                "laps",
                "lap times [s]",
                "sim time [s]",
                "outside lane [s]",
                "max |dev| [m]",
            ],
            [
                [
                    summary.task,
                    summary.track,
                    summary.laps,
                    format_lap_times(summary.lap_times_s),
                    summary.sim_time_s,
                    summary.time_outside_lane_s,
                    summary.max_abs_deviation_m,
                ]
            ],
        )
    )
    for label, path in (("video", args.video), ("rerun recording", args.rerun)):
        if path:
            print(f"{label} written to {path}")
    return 0 if summary.laps == args.laps else 1


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
