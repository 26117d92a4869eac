"""Track commands: ``tracks``, ``raceline``, ``track-info`` and ``snapshots``."""

from __future__ import annotations

import argparse
from pathlib import Path

from saferace.cli import example, values
from saferace.cli.arguments import TRACK_HELP, add_seeds_argument, add_track_arguments
from saferace.errors import SafeRaceError

#: How to drive a track of one's own, after the list of the built-in ones.
OWN_TRACK_HOWTO = (
    "Any command's --track (or track argument) takes one of these names or the path of a CSV "
    "with the header x_m,y_m,w_tr_right_m,w_tr_left_m (a closed centre line with the lane's "
    "widths right and left, as the TUM and F1TENTH track files have): "
    "saferace track-info my_track.csv checks it."
)


def register(commands: argparse._SubParsersAction) -> None:
    listing = commands.add_parser(
        "tracks",
        help="the built-in tracks: length, lane width, tightest turn; and how to use a CSV",
        epilog=example("saferace tracks"),
    )
    listing.set_defaults(command=_tracks)

    raceline = commands.add_parser(
        "raceline",
        help="minimum-curvature racing line and speed profiles of a track",
        epilog=example(
            "saferace raceline technical --out technical_raceline.csv --plot technical.png",
            "saferace raceline my_track.csv --smooth-rms-m 0.05",
        ),
    )
    add_track_arguments(raceline)
    raceline.add_argument("--out", type=Path, help="write the racing line CSV here")
    raceline.set_defaults(command=_raceline)

    info = commands.add_parser(
        "track-info",
        help="a track's length, lane widths, tightest turn, narrowed points, racing-line gain",
        epilog=example(
            "saferace track-info lab",
            "saferace track-info Monza_map.csv --smooth-rms-m 0.08 --save-track monza.csv",
        ),
    )
    add_track_arguments(info)
    info.add_argument(
        "--save-track",
        type=Path,
        help="write the lane as loaded (smoothed, narrowed) as a track CSV, to drive it anywhere",
    )
    info.set_defaults(command=_track_info)

    shots = commands.add_parser(
        "snapshots",
        help="PNGs of the onboard and chase views of tracks",
        epilog=example(
            "saferace snapshots --out results/snapshots",
            "saferace snapshots --tracks lab --randomize strong --seeds 0 1 2 3",
        ),
    )
    shots.add_argument(
        "--out", type=Path, default=Path("results/snapshots"), help="folder for the PNGs"
    )
    shots.add_argument("--tracks", nargs="*", help=f"{TRACK_HELP}s (default: all built-in)")
    shots.add_argument(
        "--image-size", type=values.image_size, default=64, help="onboard image height and width"
    )
    shots.add_argument(
        "--randomize",
        metavar="PRESET",
        help="instead, one contact sheet per track of the looks a domain-randomisation preset "
        "(none, mild, strong) draws for --seeds",
    )
    add_seeds_argument(shots, [0, 1, 2, 3], "a look per seed (--randomize)")
    shots.set_defaults(command=_snapshots)


def _report(args: argparse.Namespace, smoothed: bool = True):
    from saferace.track.report import load_track_report

    if args.smooth_keeps and args.smooth_rms_m is None:
        raise SafeRaceError("--smooth-keeps says what a smoothed lane keeps: add --smooth-rms-m")
    return load_track_report(
        args.track,
        args.car_width_m,
        args.margin_m,
        args.strict,
        args.smooth_rms_m if smoothed else None,
        args.smooth_keeps if smoothed else None,
    )


def _plot(args: argparse.Namespace, report) -> None:
    if args.plot:
        from saferace.eval.track_plots import plot_reference_lines

        plot_reference_lines(report.track, report.center, report.racing, args.plot)
        print(f"plot written to {args.plot}")


def _tracks(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table
    from saferace.track.report import builtin_track_rows

    headers = ["track", "length [m]", "lane width [m]", "tightest centre-line radius [m]"]
    print(markdown_table(headers, builtin_track_rows()))
    print()
    print(OWN_TRACK_HOWTO)
    return 0


def _raceline(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table

    report = _report(args)
    track = report.track
    rows = [
        [
            line.name,
            line.length_m,
            line.curvature_squared_integral,
            line.lap_time_s,
            float(line.vx_mps.max()),
        ]
        for line in (report.center, report.racing)
    ]
    print(f"track {track.name}: {track.length_m:.2f} m, {track.point_count} points")
    print(
        markdown_table(
            ["line", "length [m]", "int kappa^2 ds [1/m]", "lap time [s]", "top speed [m/s]"], rows
        )
    )
    if args.out:
        report.racing.to_csv(args.out)
        print(f"racing line written to {args.out}")
    _plot(args, report)
    return 0


def _track_info(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table

    report = _report(args)
    print(f"track {report.track.name}")
    if args.smooth_rms_m is None:
        print(markdown_table(["quantity", "value"], report.rows()))
    else:
        given = dict(_report(args, smoothed=False).rows())
        rows = [[name, given.get(name, "-"), value] for name, value in report.rows()]
        print(markdown_table(["quantity", "as given", "smoothed"], rows))
    if args.save_track:
        report.track.to_csv(args.save_track)
        print(f"track written to {args.save_track}")
    _plot(args, report)
    return 0


def _snapshots(args: argparse.Namespace) -> int:
    from saferace.eval.drive import contact_sheets, snapshots
    from saferace.track import builtin_track_names

    tracks = args.tracks or builtin_track_names()
    if args.randomize:
        paths = contact_sheets(args.out, tracks, args.randomize, args.seeds, args.image_size)
    else:
        paths = snapshots(args.out, tracks, args.image_size)
    for path in paths:
        print(path)
    return 0
