"""Safety commands: ``safety-table``, ``faults``, ``robustness`` and ``shift-sweep``."""

from __future__ import annotations

import argparse
from pathlib import Path

from saferace.cli import example, values
from saferace.cli.arguments import (
    TRACK_HELP,
    add_device_argument,
    add_faults_argument,
    add_filter_arguments,
    add_parallel_arguments,
    ensure_generic_model,
    filter_config,
    is_perceived,
)
from saferace.cli.options import add_config_options, config_from_args
from saferace.errors import SafeRaceError
from saferace.names import (
    AUTO,
    COMPARED_FILTERS,
    DEFAULT_FILTER_MODELS,
    DEFAULT_GAINS,
    DEFAULT_STATE_NOISE,
    GAIN_NAMES,
    GENERIC_SOURCE,
    MC_SAMPLES,
    NOISY_SAMPLES,
    VEHICLE_MODELS,
)


def register(commands: argparse._SubParsersAction) -> None:
    table = commands.add_parser(
        "safety-table",
        help="reckless agents and the expert with and without the safety filter, as a table",
        epilog=example(
            "saferace safety-table --random-tracks 11 23 --out results/safety",
            "saferace safety-table --tracks lab my_track.csv --state-source learned:lab.pt",
            "saferace safety-table --tracks lab --state-source none --out results/safety_truth",
        ),
    )
    table.add_argument("--tracks", nargs="*", help=f"{TRACK_HELP}s (default: all built-in)")
    table.add_argument(
        "--random-tracks",
        type=values.seed,
        nargs="*",
        default=[],
        metavar="SEED",
        help="also generate random tracks with these seeds (written to OUT/tracks)",
    )
    table.add_argument(
        "--out", type=Path, default=Path("results/safety"), help="folder of the tables and runs"
    )
    table.add_argument("--laps", type=values.count, default=3, help="laps per run")
    table.add_argument(
        "--max-seconds",
        type=values.positive,
        default=60.0,
        help="end a run after this much simulated time",
    )
    table.add_argument(
        "--state-noise",
        type=values.non_negative,
        nargs=2,
        default=list(DEFAULT_STATE_NOISE),
        metavar=("E_Y_M", "E_PSI_RAD"),
        help="standard deviations of the noisy state's rows",
    )
    table.add_argument(
        "--samples",
        type=values.samples,
        default=NOISY_SAMPLES,
        help="noisy state samples per step (two at least: their spread is the noise)",
    )
    table.add_argument(
        "--filter-model",
        default=AUTO,
        choices=(AUTO, *VEHICLE_MODELS),
        help="every filter's vehicle model (auto: each family's own, "
        + ", ".join(f"{model} for {kind}" for kind, model in DEFAULT_FILTER_MODELS.items())
        + ")",
    )
    table.add_argument(
        "--state-source",
        default=GENERIC_SOURCE,
        metavar="generic[:RECIPE]|learned:CKPT|none",
        help="also run the reckless agents through the filter fed this state network: robust "
        "over its conformal interval (the default of a learned source), and the paper's chance "
        "constraints and on the mean: the generic perception model (the default, built once by "
        "saferace perception) or a checkpoint's; none: only the true and noisy state",
    )
    table.add_argument(
        "--mc-samples",
        type=values.count,
        default=MC_SAMPLES,
        help="MC-dropout samples of the network",
    )
    table.add_argument(
        "--filter-gains",
        default=DEFAULT_GAINS,
        choices=GAIN_NAMES,
        help="the filter's settings (see saferace.safety.cbf.filter.GAIN_PRESETS) on the true and "
        "noisy state and in the learned source's chance-constrained rows; its robust rows take "
        "the robust mode's (--filter-gains auto of the other commands)",
    )
    table.add_argument(
        "--filters",
        nargs="+",
        default=["cbf"],
        choices=COMPARED_FILTERS,
        help="the filters to run every agent behind, compared in filter_comparison.md: the CBF "
        "with the squared slack (the paper's) or the exact l1 one, and the predictive filter",
    )
    add_faults_argument(table)
    add_parallel_arguments(table)
    add_device_argument(table)
    table.set_defaults(command=_safety_table)

    register_faults(commands)

    from saferace.experiments.robustness_config import RobustnessConfig

    robust = commands.add_parser(
        "robustness",
        help="a driver in each domain-randomisation preset's looks: completion, lane, state error",
        epilog=example(
            "saferace robustness --agent expert --track lab --out results/robustness",
            "saferace robustness --agent learned:lab.pt --task CenterLine --track lab "
            "--filter cbf --state-source learned:lab.pt --out results/robust_learned",
        ),
    )
    add_config_options(robust, RobustnessConfig(), exclude=("safety",))
    robust.add_argument(
        "--out", type=Path, required=True, help="folder of runs.jsonl and the tables"
    )
    add_filter_arguments(robust, perceived_default=GENERIC_SOURCE)
    add_device_argument(robust)
    robust.set_defaults(command=_robustness)

    sweep = commands.add_parser(
        "shift-sweep",
        help="uncertainty methods side by side: robustness folders' coverage and lane keeping "
        "against the shift severity",
        epilog=example(
            "saferace shift-sweep mc-dropout=results/mc ensemble+conformal=results/ens "
            "--out results/sweep",
        ),
    )
    sweep.add_argument(
        "methods",
        nargs="+",
        type=values.labelled_folder,
        metavar="LABEL=FOLDER",
        help="a method's label and the saferace robustness folder it drove in",
    )
    sweep.add_argument("--out", type=Path, required=True, help="folder for the table and plot")
    add_device_argument(sweep)
    sweep.set_defaults(command=_shift_sweep)


def register_faults(commands: argparse._SubParsersAction) -> None:
    """``saferace faults``: every fault at each severity, each driver, without and behind the
    default filter (:mod:`saferace.experiments.fault_table`)."""
    from saferace.experiments.fault_table_config import FaultTableConfig

    table = commands.add_parser(
        "faults",
        help="every sensor and actuator fault at each severity, each driver, without and "
        "behind the default filter, as a table",
        epilog=example(
            "saferace faults --tracks technical circuit.csv --out results/faults",
            "saferace faults --tracks lab --faults blackout frozen --severities 3 "
            "--drivers drift expert learned:lab.pt",
        ),
    )
    add_config_options(table, FaultTableConfig())
    table.add_argument(
        "--out", type=Path, default=Path("results/faults"), help="folder of the table and runs"
    )
    add_parallel_arguments(table)
    add_device_argument(table)
    table.set_defaults(command=_faults)


def _faults(args: argparse.Namespace) -> int:
    from saferace.eval.agents import check_agent_spec
    from saferace.experiments.fault_table import run_fault_table
    from saferace.experiments.fault_table_config import FaultTableConfig

    config = config_from_args(FaultTableConfig(), args)
    for driver in config.drivers:
        check_agent_spec(driver)
    ensure_generic_model(config.state_source, args.workers)
    run_fault_table(config, args.out, workers=args.workers, ray_address=args.ray)
    print((args.out / "faults.md").read_text())
    print(f"faults.md, faults.csv, faults.png and runs.jsonl written to {args.out}")
    return 0


def _safety_table(args: argparse.Namespace) -> int:
    from saferace.experiments.safety_table import run_table
    from saferace.track import builtin_track_names

    source = None if args.state_source == "none" else args.state_source
    if source is not None and not is_perceived(source):
        raise SafeRaceError(
            "--state-source must be generic[:RECIPE], learned:CHECKPOINT, MODULE:FACTORY or "
            f"none, got {source}"
        )
    ensure_generic_model(source, args.workers)
    run_table(
        list(args.tracks) if args.tracks else list(builtin_track_names()),
        args.out,
        laps=args.laps,
        max_seconds=args.max_seconds,
        noise=tuple(args.state_noise),
        samples=args.samples,
        model=args.filter_model,
        gains=args.filter_gains,
        filters=tuple(dict.fromkeys(args.filters)),
        state_source=source,
        mc_samples=args.mc_samples,
        workers=args.workers,
        ray_address=args.ray,
        random_tracks=tuple(args.random_tracks),
        faults=tuple(args.faults or ()),
    )
    print((args.out / "safety_table.md").read_text())
    print(
        f"tables, filter_comparison.md, runs, reckless_paths.png and failures/ written to "
        f"{args.out}"
    )
    return 0


def robustness_config(args: argparse.Namespace):
    """The ``RobustnessConfig`` that ``saferace robustness``'s options describe."""
    from saferace.experiments.robustness_config import RobustnessConfig

    return config_from_args(RobustnessConfig(), args, safety=filter_config(args))


def _robustness(args: argparse.Namespace) -> int:
    from saferace.experiments.robustness import run_robustness, write_report

    config = robustness_config(args)
    ensure_generic_model(config.safety.state_source)
    runs = run_robustness(config, args.out)
    print(write_report(runs, config, args.out))
    print(f"runs.jsonl, robustness.md, .csv and .png written to {args.out}")
    return 0


def _shift_sweep(args: argparse.Namespace) -> int:
    from saferace.experiments.shift_sweep import write_sweep_report

    print(write_sweep_report(dict(args.methods), args.out))
    print(f"shift_sweep.md, .csv and .png written to {args.out}")
    return 0
