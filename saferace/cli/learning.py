"""Learned-driver commands: ``collect``, ``train``, ``validate``, ``calibrate``,
``perception``, ``calibrate-track``, ``gradcam`` and ``export-minari``."""

from __future__ import annotations

import argparse
from pathlib import Path

from saferace.cli import example, values
from saferace.cli.arguments import (
    TRACK_HELP,
    add_device_argument,
    add_filter_arguments,
    add_num_envs_argument,
    add_parallel_arguments,
    ensure_generic_model,
    filter_config,
)
from saferace.cli.options import add_config_options, config_from_args
from saferace.names import (
    CONFORMAL_ALPHA,
    DEFAULT_MONITOR,
    MC_SAMPLES,
    OOD_MONITORS,
    PERCEPTION_RECIPES,
    TASKS,
)


def register(commands: argparse._SubParsersAction) -> None:
    from saferace.learning.configs import CollectionConfig, TrainConfig

    collect = commands.add_parser(
        "collect",
        help="record a round of expert-labelled frames while a driver drives",
        epilog=example(
            "saferace collect --task CenterLine --track lab --seeds 0 1 2 --perturb 0.05 "
            "--out data",
            "saferace collect --agent learned:lab.pt --track lab --filter cbf --out data",
        ),
    )
    defaults = CollectionConfig()
    add_config_options(collect, defaults, exclude=("beta",))
    add_config_options(collect, defaults.episode, prefix="episode.")
    add_config_options(collect, defaults.perturbation, prefix="perturbation.")
    collect.add_argument("--out", type=Path, required=True, help="dataset folder to add a round to")
    add_filter_arguments(collect)
    add_parallel_arguments(collect)
    add_num_envs_argument(collect)
    add_device_argument(collect)
    collect.set_defaults(command=_collect)

    train = commands.add_parser(
        "train",
        help="train the control and state networks on collection rounds",
        epilog=example(
            "saferace train data --out lab_mono.pt",
            "saferace train data/round_0000 data/round_0001 --epochs 3 --no-validation --out m.pt",
        ),
    )
    train.add_argument(
        "data", type=values.existing, nargs="+", help="dataset folders or round folders"
    )
    train.add_argument("--out", type=Path, required=True, help="checkpoint to write (NAME.pt)")
    train.add_argument(
        "--stereo",
        action="store_true",
        help="check that the rounds are stereo (the networks take the rounds' channels)",
    )
    add_config_options(train, TrainConfig(), exclude=("networks",))
    train.add_argument(
        "--no-validation",
        action="store_true",
        help="hold nothing out: train on the whole lap (score the model with saferace validate "
        "on other rounds)",
    )
    train.add_argument(
        "--samples", type=values.count, default=MC_SAMPLES, help="MC-dropout samples to score"
    )
    add_device_argument(train)
    train.set_defaults(command=_train)

    validate = commands.add_parser(
        "validate",
        help="score a checkpoint's networks on rounds (e.g. of an unseen track)",
        epilog=example("saferace validate lab_mono.pt oval_data --out results/validate"),
    )
    validate.add_argument(
        "checkpoint", type=values.existing, help="a checkpoint written by saferace train"
    )
    validate.add_argument(
        "data", type=values.existing, nargs="+", help="dataset folders or round folders"
    )
    validate.add_argument("--out", type=Path, required=True, help="folder for tables and plots")
    validate.add_argument(
        "--samples", type=values.count, default=MC_SAMPLES, help="MC-dropout samples"
    )
    add_device_argument(validate)
    validate.set_defaults(command=_validate)

    calibrate = commands.add_parser(
        "calibrate",
        help="fit a checkpoint's conformal interval and monitor on rounds it never trained on",
        description="Half the rounds' frames (at random) fit the state network's conformal "
        "calibration (normalised split conformal prediction: mean +- q std covers every output "
        "on at least 1 - alpha of exchangeable frames) and its out-of-distribution monitor; "
        "the other half measure its coverage beside the network's own interval's. The "
        "calibration is written into the checkpoint, where every learned state source uses it.",
        epilog=example("saferace calibrate lab_mono.pt oval_data --alpha 0.05 --out lab_cal.pt"),
    )
    calibrate.add_argument(
        "checkpoint", type=values.existing, help="a checkpoint written by saferace train"
    )
    calibrate.add_argument(
        "data", type=values.existing, nargs="+", help="dataset folders or round folders"
    )
    calibrate.add_argument(
        "--alpha", type=values.share, default=CONFORMAL_ALPHA, help="allowed miss rate"
    )
    calibrate.add_argument(
        "--test-share", type=values.share, default=0.5, help="share of the frames kept to test on"
    )
    calibrate.add_argument(
        "--samples", type=values.count, default=MC_SAMPLES, help="MC-dropout samples"
    )
    calibrate.add_argument(
        "--seed", type=values.seed, default=0, help="seeds the split and the dropout"
    )
    calibrate.add_argument(
        "--monitor",
        choices=OOD_MONITORS,
        default=DEFAULT_MONITOR,
        help="what the out-of-distribution monitor looks at: the state network's backbone "
        "features, its spread, or none (the interval alone, to compare)",
    )
    calibrate.add_argument(
        "--out", type=Path, required=True, help="checkpoint to write (may be the same)"
    )
    add_device_argument(calibrate)
    calibrate.set_defaults(command=_calibrate)

    perception = commands.add_parser(
        "perception",
        help="build (once) the generic perception model: a state network for tracks and looks "
        "it never saw, calibrated track by track",
        description="Random tracks (fresh seeds, random sizes and lane widths) in randomised "
        "looks, driven by "
        "the expert with steering noise and by the reckless agents behind the oracle filter; "
        "one heteroscedastic state network trained on them; its conformal interval and "
        "feature monitor fitted on other random tracks, each track a group (the largest of "
        "their per-track quantiles). Cached per recipe in $SAFERACE_CACHE (default "
        "~/.cache/saferace) with a manifest; an interrupted build resumes, a built one is "
        "reused. --state-source generic (or generic:RECIPE) feeds it to any filter.",
        epilog=example("saferace perception", "saferace perception --recipe quick"),
    )
    perception.add_argument(
        "--recipe",
        choices=PERCEPTION_RECIPES,
        default="default",
        help="default: 48 training and 12 calibration tracks, lanes 0.7-2.5 m wide (about "
        "15 min on 2 cores); quick: a few tracks (a few minutes, for a first look and the "
        "tests)",
    )
    add_parallel_arguments(perception)
    add_device_argument(perception)
    perception.set_defaults(command=_perception)

    calibrate_track = commands.add_parser(
        "calibrate-track",
        help="calibrate the generic perception model on your own track (about a minute)",
        description="The expert drives the track with steering noise from 8 starts around "
        "the lap, in the recipe's looks by turns; the generic model's interval scale and "
        "monitor threshold are fitted on those frames (split conformal). Prints the coverage "
        "and alarm rate of the pooled calibration and of the track's own on drives it was not "
        "fitted on. Cached by the track's hash beside the model: --own-track-calibration "
        "(with --state-source generic) on any command then uses it.",
        epilog=example(
            "saferace calibrate-track my_track.csv",
            "saferace calibrate-track lab oval --recipe quick",
        ),
    )
    calibrate_track.add_argument(
        "tracks", nargs="+", type=values.track, metavar="TRACK", help=TRACK_HELP
    )
    calibrate_track.add_argument(
        "--recipe", choices=PERCEPTION_RECIPES, default="default", help="the model's recipe"
    )
    add_device_argument(calibrate_track)
    calibrate_track.set_defaults(command=_calibrate_track)

    gradcam = commands.add_parser(
        "gradcam",
        help="GradCAM heat maps of every network output on frames of a track",
        description="The expert MPC laps the track on the checkpoint's camera; GradCAM maps of "
        "both networks' outputs are drawn over frames spread over that lap.",
        epilog=example("saferace gradcam lab_mono.pt --track lab --out results/gradcam"),
    )
    gradcam.add_argument(
        "checkpoint", type=values.existing, help="a checkpoint written by saferace train"
    )
    gradcam.add_argument("--track", default="lab", help=TRACK_HELP)
    gradcam.add_argument(
        "--task", default="CenterLine", choices=TASKS, help="the line the expert follows"
    )
    gradcam.add_argument(
        "--frames", type=values.count, default=6, help="frames spread over the lap"
    )
    gradcam.add_argument(
        "--layer",
        default="layer2",
        choices=["layer1", "layer2", "layer3", "layer4"],
        help="the ResNet stage whose activations GradCAM weighs (finer: earlier)",
    )
    gradcam.add_argument("--out", type=Path, required=True, help="folder for the PNGs")
    add_device_argument(gradcam)
    gradcam.set_defaults(command=_gradcam)

    export = commands.add_parser(
        "export-minari",
        help="collection or DAgger rounds as a Minari dataset (needs saferace[minari])",
        epilog=example("saferace export-minari data --name saferace/lab-center-expert-v0"),
    )
    export.add_argument("rounds", nargs="+", type=values.existing, help="round or dataset folders")
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


def collection_config(args: argparse.Namespace):
    """The ``CollectionConfig`` that ``saferace collect``'s options describe."""
    from saferace.learning.configs import CollectionConfig

    defaults = CollectionConfig()
    return config_from_args(
        defaults,
        args,
        episode=config_from_args(defaults.episode, args, prefix="episode."),
        perturbation=config_from_args(defaults.perturbation, args, prefix="perturbation."),
        safety=filter_config(args),
    )


def train_config(args: argparse.Namespace):
    """The ``TrainConfig`` that ``saferace train``'s options describe."""
    from saferace.learning.configs import TrainConfig

    config = config_from_args(TrainConfig(), args)
    return config_from_args(config, args, val_stretch=None) if args.no_validation else config


def _collect(args: argparse.Namespace) -> int:
    from saferace.eval.leaderboard import leaderboard_markdown
    from saferace.learning.collect import collect_round

    config = collection_config(args)
    ensure_generic_model(config.safety.state_source, args.workers)
    collected = collect_round(
        args.out, config, workers=args.workers, ray_address=args.ray, num_envs=args.num_envs
    )
    rows = [
        {
            "agent": config.agent,
            "task": config.task,
            "track": Path(config.track).stem,
            "filter": config.safety.as_dict(),
            "summary": summary,
            "config": {"env": {"opponents": list(config.opponents)}},
        }
        for summary in collected.episodes
    ]
    print(leaderboard_markdown(rows))
    print(f"round of {collected.frame_count} frames written to {collected.path}")
    return 0


def _train(args: argparse.Namespace) -> int:
    from saferace.learning.commands import train_and_report

    report = train_and_report(args.data, args.out, train_config(args), args.samples, args.stereo)
    _print_report(report)
    return 0


def _validate(args: argparse.Namespace) -> int:
    from saferace.learning.commands import validate_checkpoint

    _print_report(validate_checkpoint(args.checkpoint, args.data, args.out, args.samples))
    return 0


def _calibrate(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table
    from saferace.learning.recalibrate import recalibrate

    rows = recalibrate(
        args.checkpoint, args.data, args.out, args.alpha, args.samples, args.test_share,
        args.seed, monitor=args.monitor,
    )  # fmt: skip
    print(markdown_table(list(rows[0]), [list(row.values()) for row in rows]))
    print(f"written: {args.out}")
    return 0


def _perception(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table
    from saferace.learning.perception import (
        RECIPES,
        build_perception_model,
        perception_manifest,
    )

    path = build_perception_model(RECIPES[args.recipe], args.workers)
    manifest = perception_manifest(RECIPES[args.recipe])
    rows = manifest["calibration_by_track"]
    print(markdown_table(list(rows[0]), [list(row.values()) for row in rows]))
    seconds = ", ".join(f"{stage} {value:.0f} s" for stage, value in manifest["seconds"].items())
    print(f"built in {seconds}; interval scale {manifest['scale']:.3f}")
    name = "generic" if args.recipe == "default" else f"generic:{args.recipe}"
    print(f"model: {path} (--state-source {name})")
    return 0


def _calibrate_track(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table
    from saferace.learning.perception import RECIPES, ensure_perception_model
    from saferace.learning.track_calibration import track_calibration
    from saferace.track import Track

    recipe = RECIPES[args.recipe]
    ensure_perception_model(f"generic:{recipe.name}")
    rows = []
    for name in args.tracks:
        track = Track.load(name)
        _, report = track_calibration(recipe, track)
        for kind in ("pooled", "own"):
            part = report[kind]
            rows.append(
                [track.name, kind, part["scale"], f"{100 * part['coverage']:.1f}",
                 f"{100 * part['alarm_rate']:.1f}", report["held_out_frames"]]
            )  # fmt: skip
    headers = ["track", "calibration", "scale", "coverage [%]", "alarms [%]", "held-out frames"]
    print(markdown_table(headers, rows))
    print("use it: --state-source generic --own-track-calibration")
    return 0


def _gradcam(args: argparse.Namespace) -> int:
    from saferace.learning.commands import gradcam_report

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


def _export_minari(args: argparse.Namespace) -> int:
    from saferace.learning.minari_export import export_minari

    dataset = export_minari(args.rounds, args.name, args.datasets_dir, args.description)
    print(
        f"{args.name}: {dataset.total_episodes} episodes, {dataset.total_steps} steps, "
        f"in {dataset.storage.data_path}"
    )
    return 0
