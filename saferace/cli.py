"""SafeRace's command line: racing lines, driving and evaluation, the safety filter's table,
and the learned driver (collect, train, validate, gradcam)."""

from __future__ import annotations

import argparse
import functools
import logging
import sys
from pathlib import Path

from saferace.errors import SafeRaceError

DEFAULT_STATE_NOISE = (0.05, 0.05)
NOISY_SAMPLES, MC_SAMPLES = 20, 10  # the default state samples of noisy and learned sources
VEHICLE_MODELS = ("kinematic", "dynamic", "dynamic-paper")  # of the expert and the filter


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


class _HelpWithDefaults(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default in its help, unless it has none (None or off)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="saferace", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress")
    commands = parser.add_subparsers(
        required=True,
        metavar="COMMAND",
        parser_class=functools.partial(argparse.ArgumentParser, formatter_class=_HelpWithDefaults),
    )

    raceline = commands.add_parser(
        "raceline", help="minimum-curvature racing line and speed profiles of a track"
    )
    _add_track_arguments(raceline)
    raceline.add_argument("--out", type=Path, help="write the racing line CSV here")
    raceline.set_defaults(command=_raceline)

    info = commands.add_parser(
        "track-info",
        help="a track's length, lane widths, tightest turn, narrowed points, racing-line gain",
    )
    _add_track_arguments(info)
    info.add_argument(
        "--save-track",
        type=Path,
        help="write the lane as loaded (smoothed, narrowed) as a track CSV, to drive it anywhere",
    )
    info.set_defaults(command=_track_info)

    drive = commands.add_parser("drive", help="a driver laps a track; video and Rerun recording")
    _add_episode_arguments(drive, default_agent="pure-pursuit")
    drive.add_argument("--seed", type=int, default=0)
    drive.add_argument("--video", type=Path, help="write onboard + chase view MP4 here")
    drive.add_argument("--rerun", type=Path, help="write a Rerun recording (.rrd) here")
    _add_filter_arguments(drive)
    drive.set_defaults(command=_drive)

    evaluate = commands.add_parser(
        "eval", help="evaluate an agent; one JSON row per (agent, task, track, seed)"
    )
    _add_episode_arguments(evaluate, default_agent="expert")
    evaluate.add_argument("--seeds", type=int, nargs="+", default=[0])
    evaluate.add_argument(
        "--model",
        default="dynamic",
        choices=VEHICLE_MODELS,
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

    collect = commands.add_parser(
        "collect", help="record a round of expert-labelled frames while a driver drives"
    )
    _add_episode_arguments(collect, default_agent="expert")
    collect.set_defaults(laps=3)
    collect.add_argument("--seeds", type=int, nargs="+", default=[0], help="one episode per seed")
    collect.add_argument(
        "--perturb",
        type=float,
        default=0.0,
        metavar="STEER_STD_RAD",
        help="DART-style steering noise on the driver, its standard deviation (rad); the label "
        "stays the expert's",
    )
    collect.add_argument(
        "--perturb-correlation-s",
        type=float,
        default=0.5,
        help="how long a push of the steering noise lasts (its correlation time)",
    )
    collect.add_argument(
        "--model",
        default="dynamic",
        choices=VEHICLE_MODELS,
        help="vehicle model of the labelling expert MPC (and of an expert driver)",
    )
    collect.add_argument(
        "--max-seconds", type=float, help="end an episode after this much simulated time"
    )
    collect.add_argument("--out", type=Path, required=True, help="dataset folder to add a round to")
    _add_randomize_argument(collect)
    _add_filter_arguments(collect)
    collect.set_defaults(command=_collect)

    train = commands.add_parser(
        "train", help="train the control and state networks on collection rounds"
    )
    train.add_argument("data", type=Path, nargs="+", help="dataset folders or round folders")
    train.add_argument("--out", type=Path, required=True, help="checkpoint to write (NAME.pt)")
    train.add_argument(
        "--stereo",
        action="store_true",
        help="check that the rounds are stereo (the networks take the rounds' channels)",
    )
    train.add_argument(
        "--epochs", type=int, default=10, help="passes over the training frames per network"
    )
    train.add_argument("--batch-size", type=int, default=32, help="frames per Adam step")
    train.add_argument("--lr", type=float, default=1e-3, help="Adam's learning rate")
    train.add_argument(
        "--seed", type=int, default=0, help="seeds the weights, the shuffling and the dropout"
    )
    train.add_argument(
        "--val-stretch",
        type=float,
        nargs=2,
        default=[0.55, 0.7],
        metavar=("START", "END"),
        help="the stretch of the lap held out for validation, as fractions of the lap",
    )
    train.add_argument(
        "--no-validation",
        action="store_true",
        help="hold nothing out: train on the whole lap (score the model with saferace validate "
        "on other rounds)",
    )
    train.add_argument("--dropout", type=float, default=0.2, help="dropout of the heads")
    train.add_argument("--init", type=Path, help="warm-start from this checkpoint")
    train.add_argument(
        "--backbone-weights",
        type=Path,
        help="a torchvision ResNet-18 state dict (e.g. ImageNet) to start both backbones from",
    )
    train.add_argument("--samples", type=int, default=10, help="MC-dropout samples to score")
    train.set_defaults(command=_train)

    validate = commands.add_parser(
        "validate", help="score a checkpoint's networks on rounds (e.g. of an unseen track)"
    )
    validate.add_argument("checkpoint", type=Path, help="a checkpoint written by saferace train")
    validate.add_argument("data", type=Path, nargs="+", help="dataset folders or round folders")
    validate.add_argument("--out", type=Path, required=True, help="folder for tables and plots")
    validate.add_argument("--samples", type=int, default=10, help="MC-dropout samples")
    validate.set_defaults(command=_validate)

    gradcam = commands.add_parser(
        "gradcam",
        help="GradCAM heat maps of every network output on frames of a track",
        description="The expert MPC laps the track on the checkpoint's camera; GradCAM maps of "
        "both networks' outputs are drawn over frames spread over that lap.",
    )
    gradcam.add_argument("checkpoint", type=Path, help="a checkpoint written by saferace train")
    gradcam.add_argument("--track", default="lab", help="built-in track name or track CSV path")
    gradcam.add_argument(
        "--task", default="CenterLine", choices=TASKS, help="the line the expert follows"
    )
    gradcam.add_argument("--frames", type=int, default=6, help="frames spread over the lap")
    gradcam.add_argument(
        "--layer",
        default="layer2",
        choices=["layer1", "layer2", "layer3", "layer4"],
        help="the ResNet stage whose activations GradCAM weighs (finer: earlier)",
    )
    gradcam.add_argument("--out", type=Path, required=True, help="folder for the PNGs")
    gradcam.set_defaults(command=_gradcam)

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
    table.add_argument("--filter-model", default="kinematic", choices=VEHICLE_MODELS)
    table.add_argument(
        "--state-source",
        metavar="learned:CKPT",
        help="also run the reckless agents through the filter fed this state network",
    )
    table.add_argument(
        "--mc-samples", type=int, default=MC_SAMPLES, help="MC-dropout samples of the network"
    )
    _add_gains_argument(table)
    _add_parallel_arguments(table)
    table.set_defaults(command=_safety_table)

    board = commands.add_parser(
        "leaderboard",
        help="markdown table (and plots) from eval results, or the benchmark's from submissions",
    )
    board.add_argument(
        "results",
        type=Path,
        nargs="+",
        help="JSONL files written by saferace eval, or submission .json files of saferace "
        "benchmark",
    )
    board.add_argument("--csv", type=Path, help="also write the table as CSV")
    board.add_argument("--plot", type=Path, help="driven trajectories and speeds to a PNG")
    board.add_argument("--html", type=Path, help="submissions: one self-contained leaderboard page")
    board.set_defaults(command=_leaderboard)

    bench = commands.add_parser(
        "benchmark", help="the fixed evaluation protocol for one agent: a submission file"
    )
    bench.add_argument(
        "--agent",
        required=True,
        help="expert, pure-pursuit, drift, weave, speeding, learned:CHECKPOINT or MODULE:FACTORY",
    )
    bench.add_argument("--out", type=Path, required=True, help="the submission .json to write")
    _add_parallel_arguments(bench)
    bench.add_argument(
        "--mc-samples", type=int, default=MC_SAMPLES, help="MC-dropout samples of a learned agent"
    )
    bench.set_defaults(command=_benchmark)

    sysid = commands.add_parser(
        "sysid", help="identify the vehicle-model parameters from MuJoCo runs"
    )
    sysid.add_argument(
        "--out", type=Path, default=None, help="parameter file (default: stored with the car)"
    )
    sysid.set_defaults(command=_sysid)

    dagger = commands.add_parser(
        "dagger",
        help="DAgger: the expert drives, then the learned driver, the expert labels; resumable",
    )
    dagger.add_argument("--task", default="CenterLine", choices=TASKS, help="the reference line")
    dagger.add_argument("--track", default="lab", help="built-in track name or track CSV path")
    dagger.add_argument("--iterations", type=int, default=10, help="iterations after the expert's")
    dagger.add_argument(
        "--filter", default="none", choices=["none", "cbf"], help="drive through the filter"
    )
    dagger.add_argument(
        "--filter-from",
        type=int,
        default=2,
        metavar="K",
        help="the iterations after K drive through the filter (the paper's k)",
    )
    dagger.add_argument(
        "--state-source",
        default="learned",
        choices=["learned", "oracle"],
        help="what feeds the filter the lane state: the state network (perceived) or the truth",
    )
    dagger.add_argument(
        "--fork-of",
        type=Path,
        help="the unfiltered run to share iterations 0..K with (copied, not recomputed)",
    )
    dagger.add_argument("--epochs", type=int, default=9, help="training epochs per iteration")
    dagger.add_argument(
        "--min-train-steps",
        type=int,
        default=0,
        metavar="N",
        help="at least N gradient steps per training, adding epochs while the frames are few",
    )
    dagger.add_argument(
        "--max-train-steps",
        type=int,
        default=0,
        metavar="N",
        help="at most N gradient steps per training (0: no bound; from scratch too), so that "
        "an iteration costs the same however large the aggregate",
    )
    dagger.add_argument("--batch-size", type=int, default=32, help="frames per Adam step")
    dagger.add_argument(
        "--from-scratch",
        action="store_true",
        help="retrain each iteration from random weights instead of fine-tuning the last ones",
    )
    dagger.add_argument("--stereo", action="store_true", help="stereo camera pair (6 channels)")
    dagger.add_argument("--image-size", type=int, default=64, help="onboard image height and width")
    dagger.add_argument(
        "--train-fraction",
        type=float,
        default=0.7,
        help="keep frames on this first part of the lap; the rest is scored, never trained on",
    )
    dagger.add_argument("--laps", type=int, default=1, help="laps per drive")
    dagger.add_argument(
        "--expert-perturb",
        type=float,
        default=0.0,
        metavar="STEER_STD_RAD",
        help="steering noise on the expert's iteration 0 (the paper's expert drove clean)",
    )
    dagger.add_argument(
        "--beta-rampdown",
        type=int,
        default=0,
        metavar="R",
        help="the expert acts on a share 1 - i/R of iteration i's steps (0: never, as the paper)",
    )
    dagger.add_argument(
        "--model",
        default="dynamic",
        choices=VEHICLE_MODELS,
        help="vehicle model of the expert MPC",
    )
    dagger.add_argument(
        "--filter-model", default="kinematic", choices=VEHICLE_MODELS, help="the filter's model"
    )
    _add_gains_argument(dagger)
    _add_map_curvature_argument(dagger)
    _add_fuse_odometry_argument(dagger)
    dagger.add_argument(
        "--calibrate-spread",
        action="store_true",
        help="widen the state network's MC-dropout spread by the factor that matches it to "
        "its error on the previous round, which it never saw",
    )
    dagger.add_argument("--mc-samples", type=int, default=MC_SAMPLES, help="MC-dropout samples")
    dagger.add_argument(
        "--max-seconds", type=float, default=60.0, help="end a drive after this much simulated time"
    )
    dagger.add_argument("--seed", type=int, default=0, help="seeds training and dropout masks")
    dagger.add_argument("--out", type=Path, required=True, help="the run's folder")
    _add_randomize_argument(dagger)
    dagger.add_argument(
        "--episodes", type=int, default=1, help="drives per iteration (the first is reported)"
    )
    _add_parallel_arguments(dagger)
    dagger.set_defaults(command=_dagger)

    tables = commands.add_parser(
        "paper-tables",
        help="the paper's Tables 1-2 and trajectory figures: DAgger with and without the filter",
    )
    tables.add_argument(
        "--preset",
        default="quick",
        choices=["quick", "full"],
        help="quick: lab only, 3 iterations (minutes); full: both tables, 10 iterations (hours)",
    )
    tables.add_argument("--seeds", type=int, nargs="+", default=[0], help="one run set per seed")
    tables.add_argument("--out", type=Path, default=Path("results/paper"), help="output folder")
    tables.set_defaults(command=_paper_tables)

    robust = commands.add_parser(
        "robustness",
        help="a driver in each domain-randomisation preset's looks: completion, lane, state error",
    )
    _add_episode_arguments(robust, default_agent="expert")
    robust.add_argument(
        "--presets", nargs="+", default=["none", "mild", "strong"], help="looks to drive in"
    )
    robust.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="a look per seed")
    robust.add_argument(
        "--physics", action="store_true", help="the car varies with the same preset too"
    )
    robust.add_argument(
        "--monitor-state",
        metavar="learned:CKPT",
        help="score this state network beside an unfiltered run (a filtered run scores its own)",
    )
    robust.add_argument(
        "--model", default="dynamic", choices=VEHICLE_MODELS, help="the expert's vehicle model"
    )
    robust.add_argument(
        "--max-seconds", type=float, default=60.0, help="end a run after this much simulated time"
    )
    robust.add_argument("--out", type=Path, required=True, help="folder of runs.jsonl and tables")
    _add_filter_arguments(robust)
    robust.set_defaults(command=_robustness)

    export = commands.add_parser(
        "export-minari",
        help="collection or DAgger rounds as a Minari dataset (minari.load_dataset)",
    )
    export.add_argument("rounds", nargs="+", type=Path, help="round or dataset folders")
    export.add_argument(
        "--name", required=True, help="dataset id, e.g. saferace/lab-racing-expert-v0"
    )
    export.add_argument(
        "--datasets-dir",
        type=Path,
        help="Minari's dataset root (default: $MINARI_DATASETS_PATH or ~/.minari/datasets)",
    )
    export.add_argument("--description", help="the dataset's description (default: generated)")
    export.set_defaults(command=_export_minari)

    shots = commands.add_parser("snapshots", help="PNGs of the onboard and chase views of tracks")
    shots.add_argument("--out", type=Path, default=Path("results/snapshots"))
    shots.add_argument("--tracks", nargs="*", help="track names or CSVs (default: all built-in)")
    shots.add_argument("--image-size", type=int, default=64)
    shots.add_argument(
        "--randomize",
        metavar="PRESET",
        help="instead, one contact sheet per track of the looks a domain-randomisation preset "
        "(none, mild, strong) draws for --seeds",
    )
    shots.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    shots.set_defaults(command=_snapshots)
    return parser


TASKS = ("CenterLine", "RacingLine")


def _add_episode_arguments(parser: argparse.ArgumentParser, default_agent: str) -> None:
    """The arguments of one driven episode, shared by ``drive`` and ``eval``."""
    parser.add_argument(
        "--task", default="RacingLine", choices=TASKS, help="the reference line to follow"
    )
    parser.add_argument(
        "--track", default="technical", help="built-in track name or track CSV path"
    )
    parser.add_argument(
        "--agent",
        default=default_agent,
        help="expert, pure-pursuit, drift, weave, speeding, learned:CHECKPOINT or MODULE:FACTORY",
    )
    parser.add_argument("--laps", type=int, default=1, help="laps per episode")
    parser.add_argument("--image-size", type=int, default=64, help="onboard image height and width")
    parser.add_argument("--stereo", action="store_true", help="stereo camera pair (6 channels)")
    parser.add_argument(
        "--mc-samples",
        type=int,
        default=MC_SAMPLES,
        help="MC-dropout samples per step of a learned agent",
    )


FILTER_GAINS = ("paper", "grip", "tuned")  # the keys of saferace.safety.filter.GAIN_PRESETS
SMOOTHING_KEEPS = ("widths", "boundaries")  # saferace.track.smoothing.SMOOTHING_KEEPS


def _add_filter_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--filter", default="none", choices=["none", "cbf"], help="wrap the agent in a filter"
    )
    parser.add_argument(
        "--filter-model", default="kinematic", choices=VEHICLE_MODELS, help="the filter's model"
    )
    parser.add_argument(
        "--state-noise",
        type=float,
        nargs=2,
        metavar=("E_Y_M", "E_PSI_RAD"),
        help="the filter sees noisy state samples with these standard deviations",
    )
    parser.add_argument(
        "--state-source",
        default="oracle",
        metavar="oracle|noisy|learned:CKPT",
        help="what feeds the filter the lane state: the truth, noisy truth (--state-noise, "
        "default 0.05 0.05), or a checkpoint's state network (the perceived state)",
    )
    parser.add_argument(
        "--samples",
        type=int,
        help="state samples per step: of the noisy oracle (default 20), or the state network's "
        "MC-dropout samples (default 10)",
    )
    parser.add_argument(
        "--deterministic",
        action="store_true",
        help="filter on the samples' mean instead of with chance constraints",
    )
    _add_map_curvature_argument(parser)
    _add_fuse_odometry_argument(parser)
    _add_gains_argument(parser)
    parser.add_argument(
        "--spread-scale",
        type=float,
        nargs=3,
        metavar=("E_Y", "E_PSI", "KAPPA"),
        help="widen the state samples' spread about their mean by these factors (a calibration "
        "of the state network's, see `saferace dagger --calibrate-spread`)",
    )


def _add_map_curvature_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--map-curvature",
        action="store_true",
        help="the filter takes the centerline's curvature from the map at the car's s instead "
        "of from the state source (a state network judges it worst)",
    )


def _add_fuse_odometry_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--fuse-odometry",
        action="store_true",
        help="fuse the state samples with odometry (yaw rate, speed, the map's curvature) in a "
        "Kalman filter that leaves out outliers",
    )


def _add_gains_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--filter-gains",
        default="grip",
        choices=FILTER_GAINS,
        help="the filter's settings: the paper's gain, the same with the steering held within "
        "the tyres' grip (drivable at racing speed), or the gains measured to cost the expert "
        "least on the built-in tracks",
    )


def _filter_config(args: argparse.Namespace):
    from saferace.eval.filters import FilterConfig

    source = args.state_source
    learned = source.startswith("learned:")
    if source not in ("oracle", "noisy") and not learned:
        raise SafeRaceError(
            f"unknown --state-source {source!r}: use oracle, noisy or learned:CHECKPOINT"
        )
    noise = args.state_noise
    if source == "noisy" and noise is None:
        noise = DEFAULT_STATE_NOISE
    if learned and noise is not None:
        raise SafeRaceError("--state-noise is for the noisy oracle, not a learned state source")
    noisy = noise is not None
    samples = args.samples if args.samples is not None else (NOISY_SAMPLES if noisy else MC_SAMPLES)
    if noisy and samples < 2:
        raise SafeRaceError(f"--samples must be at least 2 for noisy state, got {samples}")
    if samples < 1:
        raise SafeRaceError(f"--samples must be at least 1, got {samples}")
    if noisy and min(noise) < 0:
        raise SafeRaceError(f"--state-noise must not be negative, got {noise}")
    scale = args.spread_scale
    if args.filter == "none" and (
        noisy
        or args.deterministic
        or source != "oracle"
        or args.map_curvature
        or scale
        or args.fuse_odometry
    ):
        raise SafeRaceError(
            "--state-source, --state-noise, --deterministic, --map-curvature, --spread-scale and "
            "--fuse-odometry need --filter cbf"
        )
    if args.fuse_odometry and not (noisy or learned):
        raise SafeRaceError("--fuse-odometry fuses a noisy or learned --state-source")
    if scale is not None and min(scale) <= 0.0:
        raise SafeRaceError(f"--spread-scale needs 3 positive factors, got {scale}")
    return FilterConfig(
        kind=args.filter,
        model=args.filter_model,
        state_noise=None if noise is None else tuple(noise),
        samples=samples,
        probabilistic=not args.deterministic,
        gains=args.filter_gains,
        state_source=source if learned else None,
        map_curvature=args.map_curvature,
        spread_scale=None if scale is None else tuple(scale),
        fuse_odometry=args.fuse_odometry,
    )


def _add_track_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("track", help="built-in track name or track CSV path")
    parser.add_argument("--car-width-m", type=float, default=None, help="car width (default 0.30)")
    parser.add_argument(
        "--margin-m", type=float, default=None, help="extra clearance (default 0.10)"
    )
    parser.add_argument("--plot", type=Path, help="draw the track, both lines and speeds to a PNG")
    parser.add_argument(
        "--strict",
        action="store_true",
        help="refuse a track whose turns are tighter than its half width instead of narrowing it",
    )
    parser.add_argument(
        "--smooth-rms-m",
        type=float,
        help="smooth a noisy centre line: a spline that moves its points by this RMS distance "
        "(e.g. 0.05)",
    )
    parser.add_argument(
        "--smooth-keeps",
        choices=SMOOTHING_KEEPS,
        help="what a smoothed lane keeps: the given widths (default: its boundaries move with the "
        "centre line, as the F1TENTH collection's lanes) or the given boundaries (measured edges)",
    )


def _track_report(args: argparse.Namespace, smooth_rms_m: float | None):
    """The track of ``args`` (smoothed by ``smooth_rms_m``) and its report, as
    ``_add_track_arguments`` asked."""
    from dataclasses import replace

    from saferace.track import Track, VehicleEnvelope
    from saferace.track.raceline import RacingLineSettings
    from saferace.track.report import track_report

    if args.smooth_keeps and args.smooth_rms_m is None:
        raise SafeRaceError("--smooth-keeps says what a smoothed lane keeps: add --smooth-rms-m")
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
    track = Track.load(
        args.track,
        car_width_m=envelope.width_m,
        strict=args.strict,
        smooth_rms_m=smooth_rms_m,
        smooth_keeps=args.smooth_keeps or "widths",
    )
    return track_report(track, envelope, settings)


def _plot_track_report(args: argparse.Namespace, report) -> None:
    if args.plot:
        from saferace.eval.track_plots import plot_reference_lines

        plot_reference_lines(report.track, report.center, report.racing, args.plot)
        print(f"plot written to {args.plot}")


def _raceline(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table

    report = _track_report(args, args.smooth_rms_m)
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
    _plot_track_report(args, report)
    return 0


def _track_info(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table

    report = _track_report(args, args.smooth_rms_m)
    print(f"track {report.track.name}")
    if args.smooth_rms_m is None:
        print(markdown_table(["quantity", "value"], report.rows()))
    else:
        given = dict(_track_report(args, None).rows())
        rows = [[name, given.get(name, "-"), value] for name, value in report.rows()]
        print(markdown_table(["quantity", "as given", "smoothed"], rows))
    if args.save_track:
        report.track.to_csv(args.save_track)
        print(f"track written to {args.save_track}")
    _plot_track_report(args, report)
    return 0


def _drive(args: argparse.Namespace) -> int:
    from saferace.eval.drive import drive
    from saferace.eval.leaderboard import leaderboard_markdown
    from saferace.eval.runner import result_row

    _check_count("--laps", args.laps)
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
        mc_samples=args.mc_samples,
        safety=_filter_config(args),
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
    from saferace.eval.runner import evaluate, max_steps_for

    _check_count("--laps", args.laps)
    safety = _filter_config(args)
    rows = evaluate(
        args.agent,
        args.task,
        args.track,
        args.seeds,
        laps=args.laps,
        model=args.model,
        out=args.out,
        env_kwargs={
            "max_steps": max_steps_for(args.max_seconds),
            "image_size": (args.image_size, args.image_size),
            "stereo": args.stereo,
        },
        safety=safety,
        mc_samples=args.mc_samples,
    )
    print(leaderboard_markdown(rows))
    print(f"{len(rows)} rows appended to {args.out}")
    return 0


def _safety_table(args: argparse.Namespace) -> int:
    from saferace.eval.safety_table import RANDOM_TRACK_RADIUS_M, run_table
    from saferace.track import builtin_track_names
    from saferace.track.random_track import write_random_track

    _check_count("--laps", args.laps)
    if args.max_seconds <= 0 or args.samples < 2 or min(args.state_noise) < 0:
        raise SafeRaceError("need --max-seconds > 0, --samples >= 2, --state-noise >= 0")
    if args.state_source is not None and not args.state_source.startswith("learned:"):
        raise SafeRaceError(f"--state-source must be learned:CHECKPOINT, got {args.state_source}")
    _check_count("--mc-samples", args.mc_samples)
    _check_count("--workers", args.workers)
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
        state_source=args.state_source,
        mc_samples=args.mc_samples,
        workers=args.workers,
        ray_address=args.ray,
    )
    print((args.out / "safety_table.md").read_text())
    print(f"tables, runs and reckless_paths.png written to {args.out}")
    return 0


def _collect(args: argparse.Namespace) -> int:
    from saferace.eval.leaderboard import leaderboard_markdown
    from saferace.learning.collect import CollectionConfig, Perturbation, collect_round

    _check_count("--laps", args.laps)
    perturbation = Perturbation(args.perturb, args.perturb_correlation_s)
    config = CollectionConfig(
        agent=args.agent,
        task=args.task,
        track=args.track,
        seeds=tuple(args.seeds),
        laps=args.laps,
        max_seconds=args.max_seconds,
        perturbation=perturbation,
        safety=_filter_config(args),
        expert_model=args.model,
        image_size=(args.image_size, args.image_size),
        stereo=args.stereo,
        mc_samples=args.mc_samples,
        randomize=args.randomize,
    )
    collected = collect_round(args.out, config)
    rows = [
        {"agent": args.agent, "task": args.task, "track": Path(args.track).stem, "summary": s}
        for s in collected.episodes
    ]
    print(leaderboard_markdown(rows))
    print(f"round of {collected.frame_count} frames written to {collected.path}")
    return 0


def _train(args: argparse.Namespace) -> int:
    from saferace.learning.commands import train_and_report
    from saferace.learning.training import TrainConfig

    _check_count("--samples", args.samples)

    config = TrainConfig(
        epochs=args.epochs,
        batch_size=args.batch_size,
        learning_rate=args.lr,
        seed=args.seed,
        val_stretch=None if args.no_validation else tuple(args.val_stretch),
        dropout=args.dropout,
        init=None if args.init is None else str(args.init),
        backbone_weights=None if args.backbone_weights is None else str(args.backbone_weights),
    )
    report = train_and_report(args.data, args.out, config, args.samples, args.stereo)
    _print_report(report)
    return 0


def _validate(args: argparse.Namespace) -> int:
    from saferace.learning.commands import validate_checkpoint

    _check_count("--samples", args.samples)
    _print_report(validate_checkpoint(args.checkpoint, args.data, args.out, args.samples))
    return 0


def _gradcam(args: argparse.Namespace) -> int:
    from saferace.learning.commands import gradcam_report

    _check_count("--frames", args.frames)
    report = gradcam_report(
        args.checkpoint, args.track, args.out, args.task, args.frames, args.layer
    )
    _print_report(report)
    return 0


def _print_report(report) -> None:
    from saferace.learning.validation import validation_markdown

    if report.rows:
        print(validation_markdown(report.rows))
    for path in report.files:
        print(f"written: {path}")


def _benchmark(args: argparse.Namespace) -> int:
    from saferace.eval.benchmark import run_benchmark

    _check_count("--workers", args.workers)
    result = run_benchmark(
        args.agent,
        args.out,
        workers=args.workers,
        mc_samples=args.mc_samples,
        ray_address=args.ray,
    )
    score = "-" if result["score"] is None else f"{result['score']:.1f}"
    with_filter = result["score_with_filter"]
    print(
        f"{args.agent}: score {score}, with the filter "
        f"{'-' if with_filter is None else f'{with_filter:.1f}'}; submission written to {args.out}"
    )
    return 0


def _submission_leaderboard(args: argparse.Namespace) -> int:
    from saferace.eval.benchmark import load_suite, read_submission
    from saferace.eval.leaderboard_html import COLUMNS, leaderboard_html, leaderboard_rows
    from saferace.eval.tables import markdown_table, write_csv

    if args.plot:
        raise SafeRaceError("--plot is for eval results; a submissions' page has --html")
    submissions = [read_submission(path) for path in args.results]
    rows = leaderboard_rows(submissions)
    print(markdown_table(COLUMNS, [["-" if v is None else v for v in row] for row in rows]))
    if args.csv:
        write_csv(args.csv, COLUMNS, rows)
        print(f"table written to {args.csv}")
    if args.html:
        args.html.parent.mkdir(parents=True, exist_ok=True)
        args.html.write_text(leaderboard_html(submissions, load_suite()))
        print(f"page written to {args.html}")
    return 0


def _leaderboard(args: argparse.Namespace) -> int:
    submissions = [path.suffix == ".json" for path in args.results]
    if any(submissions):
        if not all(submissions):
            raise SafeRaceError("give either eval results (.jsonl) or submissions (.json)")
        return _submission_leaderboard(args)
    if args.html:
        raise SafeRaceError("--html makes the benchmark's page: give submission .json files")
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


def _dagger(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table
    from saferace.learning.dagger import METRIC_COLUMNS, DaggerConfig, DaggerRun

    _check_count("--laps", args.laps)
    _check_count("--mc-samples", args.mc_samples)
    if args.fork_of is not None and args.filter != "cbf":
        raise SafeRaceError("--fork-of makes a filtered fork: add --filter cbf")
    if args.calibrate_spread and args.filter != "cbf":
        raise SafeRaceError("--calibrate-spread widens what the filter believes: add --filter cbf")
    if args.fuse_odometry and (args.filter != "cbf" or args.state_source != "learned"):
        raise SafeRaceError(
            "--fuse-odometry fuses the state network's samples: add --filter cbf "
            "(and keep --state-source learned)"
        )
    config = DaggerConfig(
        task=args.task,
        track=args.track,
        iterations=args.iterations,
        filter=args.filter,
        filter_from=args.filter_from,
        state_source=args.state_source,
        epochs=args.epochs,
        min_train_steps=args.min_train_steps,
        max_train_steps=args.max_train_steps,
        batch_size=args.batch_size,
        warm_start=not args.from_scratch,
        stereo=args.stereo,
        image_size=args.image_size,
        train_fraction=args.train_fraction,
        laps=args.laps,
        expert_perturb=args.expert_perturb,
        seed=args.seed,
        expert_model=args.model,
        filter_model=args.filter_model,
        filter_gains=args.filter_gains,
        map_curvature=args.map_curvature,
        calibrate_spread=args.calibrate_spread,
        fuse_odometry=args.fuse_odometry,
        mc_samples=args.mc_samples,
        beta_rampdown=args.beta_rampdown,
        max_seconds=args.max_seconds,
        randomize=args.randomize,
        episodes=args.episodes,
    )
    _check_count("--workers", args.workers)
    rows = DaggerRun(
        args.out, config, fork_of=args.fork_of, workers=args.workers, ray_address=args.ray
    ).run()
    print(
        markdown_table(
            METRIC_COLUMNS, [[_cell(row.get(c)) for c in METRIC_COLUMNS] for row in rows]
        )
    )
    print(f"metrics written to {args.out / 'metrics.csv'} and metrics.jsonl")
    return 0


def _paper_tables(args: argparse.Namespace) -> int:
    from saferace.learning.paper_tables import run_paper_tables

    for path in run_paper_tables(args.preset, list(args.seeds), args.out):
        if path.suffix == ".md":
            print(path.read_text())
        print(f"written: {path}")
    return 0


def _cell(value):
    return "-" if value is None else value


def _check_count(flag: str, value: int) -> None:
    if value < 1:
        raise SafeRaceError(f"{flag} must be at least 1, got {value}")


def _robustness(args: argparse.Namespace) -> int:
    from saferace.eval.robustness import (
        TABLE_COLUMNS,
        RobustnessConfig,
        plot_robustness,
        robustness_rows,
        run_robustness,
    )
    from saferace.eval.tables import markdown_table, write_csv

    _check_count("--laps", args.laps)
    monitor = args.monitor_state
    if monitor is not None and not monitor.startswith("learned:"):
        raise SafeRaceError(f"--monitor-state must be learned:CHECKPOINT, got {monitor}")
    config = RobustnessConfig(
        agent=args.agent,
        task=args.task,
        track=args.track,
        presets=tuple(args.presets),
        seeds=tuple(args.seeds),
        laps=args.laps,
        max_seconds=args.max_seconds,
        physics=args.physics,
        safety=_filter_config(args),
        monitor_state_source=monitor,
        model=args.model,
        image_size=args.image_size,
        stereo=args.stereo,
        mc_samples=args.mc_samples,
    )
    runs = run_robustness(config, args.out)
    rows = robustness_rows(runs, config.presets, config.laps)
    table = markdown_table(TABLE_COLUMNS, rows)
    (args.out / "robustness.md").write_text(table + "\n")
    write_csv(args.out / "robustness.csv", TABLE_COLUMNS, rows)
    plot_robustness(runs, config.presets, args.out / "robustness.png")
    print(table)
    print(f"runs.jsonl, robustness.md, .csv and .png written to {args.out}")
    return 0


def _export_minari(args: argparse.Namespace) -> int:
    from saferace.learning.minari_export import export_minari

    dataset = export_minari(args.rounds, args.name, args.datasets_dir, args.description)
    print(
        f"{args.name}: {dataset.total_episodes} episodes, {dataset.total_steps} steps, "
        f"in {dataset.storage.data_path}"
    )
    return 0


def _add_parallel_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workers", type=int, default=1, help="runs at once, in processes")
    parser.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="one Ray task per run: on a Ray cluster at ADDRESS, or a local Ray instance",
    )


def _add_randomize_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--randomize",
        default="none",
        metavar="PRESET",
        help="visual domain randomisation: none, mild or strong (a look per episode seed)",
    )


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
