"""Experiment commands: ``dagger`` and ``paper-tables``."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from saferace.cli import example, values
from saferace.cli.arguments import (
    add_device_argument,
    add_num_envs_argument,
    add_parallel_arguments,
    add_seeds_argument,
    add_slack_argument,
    ensure_generic_model,
)
from saferace.cli.options import add_config_options, config_from_args
from saferace.errors import SafeRaceError
from saferace.names import (
    AUTO,
    DAGGER_STATE_SOURCES,
    GENERIC_SOURCE,
    PAPER_PRESETS,
    PERCEPTION_RECIPES,
    STATE_UNCERTAINTY_METHODS,
)


def register(commands: argparse._SubParsersAction) -> None:
    from saferace.learning.configs import DaggerConfig

    dagger = commands.add_parser(
        "dagger",
        help="DAgger: the expert drives, then the learned driver, the expert labels; resumable",
        epilog=example(
            "saferace dagger --task CenterLine --track lab --iterations 3 --out runs/lab",
            "saferace dagger --track lab --iterations 3 --filter cbf --filter-from 1 "
            "--fork-of runs/lab --out runs/lab_cbf",
        ),
    )
    defaults = DaggerConfig()
    add_config_options(dagger, defaults)
    training = dagger.add_argument_group("training")
    add_config_options(
        training,
        defaults.training,
        prefix="training.",
        exclude=("val_stretch", "init", "backbone_weights", "state_uncertainty"),
        command=dagger,
    )
    training.add_argument(
        "--state-uncertainty",
        dest="training.state_uncertainty",
        default=AUTO,
        choices=(AUTO, *STATE_UNCERTAINTY_METHODS),
        help="the state network's uncertainty (see saferace train); auto: a deep ensemble "
        "where the filter takes the perceived state in the robust mode (the default with "
        "--filter cbf), MC dropout otherwise, and with --fork-of the method of the run it "
        "forks",
    )
    add_config_options(
        dagger.add_argument_group("driving"),
        defaults.collection,
        prefix="collection.",
        command=dagger,
    )
    group = dagger.add_argument_group("safety filter")
    add_config_options(
        group,
        defaults.filter,
        prefix="filter.",
        exclude=("state_noise", "samples", "state_source", "spread_scale"),
        command=dagger,
    )
    group.add_argument(
        "--state-source",
        default=GENERIC_SOURCE,
        choices=(
            *DAGGER_STATE_SOURCES,
            *(f"{GENERIC_SOURCE}:{recipe}" for recipe in PERCEPTION_RECIPES),
        ),
        help="what feeds the filter the lane state: the generic perception model (the default, "
        "built once by saferace perception; generic:RECIPE for another recipe), the run's own "
        "state network (learned: the paper's) or the truth",
    )
    dagger.add_argument(
        "--fork-of",
        type=values.existing,
        help="the unfiltered run to share iterations 0..K with (linked, not recomputed)",
    )
    dagger.add_argument("--out", type=Path, required=True, help="the run's folder")
    add_parallel_arguments(dagger)
    add_num_envs_argument(dagger)
    add_device_argument(dagger)
    dagger.set_defaults(command=_dagger)

    tables = commands.add_parser(
        "paper-tables",
        help="the paper's Tables 1-2 and trajectory figures: DAgger with and without the filter",
        epilog=example(
            "saferace paper-tables --preset quick --out results/paper",
            "saferace paper-tables --preset full --seeds 0 1 2 --out results/paper_full",
        ),
    )
    tables.add_argument(
        "--preset",
        default="quick",
        choices=PAPER_PRESETS,
        help="quick: lab only, 3 iterations (minutes); full: both tables, 10 iterations (hours)",
    )
    tables.add_argument(
        "--state-uncertainty",
        default="mc-dropout",
        choices=STATE_UNCERTAINTY_METHODS,
        help="the state networks' uncertainty in every run: MC dropout (the paper's), a deep "
        "ensemble or a MIMO ensemble (see saferace train)",
    )
    add_slack_argument(tables, "every filtered run and drive")
    add_seeds_argument(tables, [0], "one run set per seed")
    tables.add_argument("--out", type=Path, default=Path("results/paper"), help="output folder")
    add_device_argument(tables)
    tables.set_defaults(command=_paper_tables)


def dagger_config(args: argparse.Namespace):
    """The ``DaggerConfig`` that ``saferace dagger``'s options describe."""
    from saferace.learning.configs import DaggerConfig

    filtered = args.__dict__["filter.kind"] != "none"
    if args.fork_of is not None and not filtered:
        raise SafeRaceError("--fork-of makes a filtered fork: add --filter cbf")
    if args.calibrate_spread and not filtered:
        raise SafeRaceError("--calibrate-spread widens what the filter believes: add --filter cbf")
    perceived = args.state_source != "oracle"
    if args.__dict__["filter.fuse_odometry"] and not (filtered and perceived):
        raise SafeRaceError(
            "--fuse-odometry fuses a state network's samples: add --filter cbf "
            "(and a --state-source other than oracle)"
        )
    method = args.__dict__["training.state_uncertainty"]
    if method == AUTO and args.fork_of is not None:  # the networks of the run it shares
        method = forked_state_uncertainty(args.fork_of)
    uncertainty = args.__dict__["filter.uncertainty"]
    if uncertainty == AUTO and args.calibrate_spread:  # an option of the chance constraints
        uncertainty = "chance"
    defaults = DaggerConfig()
    return config_from_args(
        defaults,
        args,
        training=config_from_args(
            defaults.training, args, prefix="training.", state_uncertainty=method
        ),
        collection=config_from_args(defaults.collection, args, prefix="collection."),
        filter=config_from_args(
            defaults.filter,
            args,
            prefix="filter.",
            state_source=args.state_source if perceived else None,
            uncertainty=uncertainty,
        ),
    )


def forked_state_uncertainty(base: Path) -> str:
    """The state networks' uncertainty method of the DAgger run in ``base`` (a fork shares
    its networks, so ``auto`` takes it): MC dropout where the run predates the option."""
    from saferace.learning.run_layout import RunLayout

    layout = RunLayout(base)
    stored = layout.stored_fingerprint()
    if stored is None:
        raise SafeRaceError(
            f"--fork-of {base} holds no DAgger run ({layout.run_file.name} is missing)"
        )
    return stored.get("state_uncertainty", "mc-dropout")


def _dagger(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table
    from saferace.learning.dagger import METRIC_COLUMNS, DaggerRun

    config = dagger_config(args)
    if config.filters:
        ensure_generic_model(config.filter.state_source, args.workers)
    rows = DaggerRun(
        args.out,
        config,
        fork_of=args.fork_of,
        workers=args.workers,
        ray_address=args.ray,
        num_envs=args.num_envs,
    ).run()
    cells = [["-" if row.get(c) is None else row.get(c) for c in METRIC_COLUMNS] for row in rows]
    print(markdown_table(METRIC_COLUMNS, cells))
    print(f"metrics written to {args.out / 'metrics.csv'} and metrics.jsonl")
    return 0


def _paper_tables(args: argparse.Namespace) -> int:
    from saferace.experiments.paper import run_paper_tables
    from saferace.experiments.paper.presets import PRESETS

    preset = replace(
        PRESETS[args.preset], state_uncertainty=args.state_uncertainty, slack=args.filter_slack
    )
    for path in run_paper_tables(preset, list(args.seeds), args.out):
        if path.suffix == ".md":
            print(path.read_text())
        print(f"written: {path}")
    return 0
