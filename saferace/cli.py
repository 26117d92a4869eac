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
        "--margin-m", type=float, default=None, help="extra clearance (default 0.05)"
    )
    raceline.add_argument(
        "--plot", type=Path, help="draw the track, both lines and speeds to a PNG"
    )
    raceline.set_defaults(command=_raceline)
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
