"""Argument groups that several commands share: episode, filter, track, parallel, look."""

from __future__ import annotations

import argparse
from pathlib import Path

from saferace.cli import values
from saferace.cli.options import add_config_options
from saferace.errors import SafeRaceError
from saferace.names import (
    AUTO,
    DEFAULT_STATE_NOISE,
    DEVICE_HELP,
    DRIVING_TASKS,
    FAULTS_HELP,
    GENERIC_SOURCE,
    MC_SAMPLES,
    NOISY_SAMPLES,
    OPPONENTS_HELP,
    PERCEPTION_RECIPES,
    RANDOMIZATION_PRESETS,
    SLACK_PENALTIES,
    SMOOTHING_KEEPS,
    SQUARED_SLACK,
)
from saferace.track import builtin_track_names

AGENT_HELP = "expert, pure-pursuit, drift, weave, speeding, learned:CHECKPOINT or MODULE:FACTORY"
TRACK_HELP = (
    f"built-in track ({', '.join(builtin_track_names())}; saferace tracks describes them) or "
    "track CSV path"
)


def add_episode_arguments(parser: argparse.ArgumentParser, default_agent: str) -> None:
    """The arguments of one driven episode: task, track, agent, laps, camera, opponents,
    sensor faults."""
    group = parser.add_argument_group("episode")
    group.add_argument(
        "--task",
        default="RacingLine",
        choices=DRIVING_TASKS,
        help="the reference line to follow (Overtake: the racing line behind a slower car)",
    )
    group.add_argument("--track", type=values.track, default="technical", help=TRACK_HELP)
    group.add_argument("--agent", default=default_agent, help=AGENT_HELP)
    group.add_argument("--laps", type=values.count, default=1, help="laps per episode")
    group.add_argument(
        "--yes",
        action="store_true",
        help=f"run even where the laps asked for are more than {LONG_DRIVE_H:g} h of driving",
    )
    group.add_argument(
        "--image-size", type=values.image_size, default=64, help="onboard image height and width"
    )
    group.add_argument("--stereo", action="store_true", help="stereo camera pair (6 channels)")
    group.add_argument(
        "--mc-samples",
        type=values.count,
        default=MC_SAMPLES,
        help="MC-dropout samples per step of a learned agent",
    )
    group.add_argument(
        "--opponents", nargs="+", metavar="POLICY[:FIELD=VALUE,...]", help=OPPONENTS_HELP
    )
    add_faults_argument(group)


def add_faults_argument(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--faults``: sensor and actuator faults, each ``NAME[:KEY=VALUE,...]``."""
    parser.add_argument(
        "--faults", nargs="+", type=values.fault, metavar="NAME[:KEY=VALUE,...]", help=FAULTS_HELP
    )


def add_seeds_argument(parser: argparse.ArgumentParser, default: list[int], help: str) -> None:
    """``--seeds``: distinct seeds (a seed twice would run one episode twice)."""
    parser.add_argument(
        "--seeds", type=values.seed, nargs="+", action=values.Distinct, default=default, help=help
    )


#: Simulated driving (hours) beyond which a run asks for ``--yes`` (:func:`check_drive_length`).
LONG_DRIVE_H = 1.0
#: A fast car's mean speed (m/s), for the shortest the laps asked for can take.
FAST_MEAN_SPEED_MPS = 6.0


def check_drive_length(args: argparse.Namespace) -> None:
    """Refuse, in one line with the estimate, laps that a fast car would take more than
    :data:`LONG_DRIVE_H` hours of simulated driving over (every step is kept in memory),
    unless ``--yes``: ``eval --laps 1000000`` printed nothing for minutes before."""
    from saferace.track import Track

    episodes = len(getattr(args, "seeds", [0]))
    length_m = Track.load(args.track).length_m
    hours = args.laps * episodes * length_m / FAST_MEAN_SPEED_MPS / 3600.0
    if hours > LONG_DRIVE_H and not args.yes:
        raise SafeRaceError(
            f"argument --laps: {args.laps:,} laps of {Path(args.track).stem} ({length_m:.0f} m) "
            f"x {episodes} episode(s) is at least {hours:,.1f} h of simulated driving, every "
            "step kept in memory; pass --yes to run it"
        )


def add_filter_arguments(
    parser: argparse.ArgumentParser, perceived_default: str = "oracle"
) -> None:
    """The safety filter's options (generated from ``FilterConfig``) and its state source:
    ``perceived_default`` where a filter is asked for without one (and no monitor's source
    is named), else the truth."""
    from saferace.eval.filter_config import FilterConfig

    group = parser.add_argument_group("safety filter")
    add_config_options(
        group,
        FilterConfig(),
        prefix="filter.",
        exclude=("state_noise", "samples", "state_source"),
        command=parser,
    )
    group.add_argument(
        "--state-source",
        metavar="oracle|noisy|generic[:RECIPE]|learned:CKPT|MODULE:FACTORY",
        help="what feeds the filter the lane state: the truth, noisy truth (--state-noise, "
        f"default {DEFAULT_STATE_NOISE[0]} {DEFAULT_STATE_NOISE[1]}), the generic perception "
        "model (built once by saferace perception, recipe default or "
        f"{'|'.join(PERCEPTION_RECIPES)}), a checkpoint's state network, or a perception "
        "method of your own (FACTORY(setup) in MODULE, from the current folder too; see "
        f"saferace.safety.uncertainty.perception) (default: {perceived_default} with a filter)",
    )
    parser.set_defaults(perceived_default=perceived_default)
    group.add_argument(
        "--state-noise",
        type=values.non_negative,
        nargs=2,
        metavar=("E_Y_M", "E_PSI_RAD"),
        help="the filter sees noisy state samples with these standard deviations",
    )
    group.add_argument(
        "--samples",
        type=values.count,
        help=f"state samples per step: of the noisy oracle (default {NOISY_SAMPLES}), or the "
        f"state network's MC-dropout samples (default {MC_SAMPLES})",
    )


def filter_config(args: argparse.Namespace):
    """The ``FilterConfig`` that :func:`add_filter_arguments`' options describe."""
    from saferace.cli.options import config_from_args
    from saferace.eval.filter_config import FilterConfig

    option = vars(args)
    source = args.state_source or default_state_source(args)
    learned = is_perceived(source)
    if not learned and source not in ("oracle", "noisy"):
        raise SafeRaceError(
            f"unknown --state-source {source!r}: use oracle, noisy, generic[:RECIPE], "
            "learned:CHECKPOINT or MODULE:FACTORY"
        )
    noise = args.state_noise
    if source == "noisy" and noise is None:
        noise = DEFAULT_STATE_NOISE
    if learned and noise is not None:
        raise SafeRaceError("--state-noise is for the noisy oracle, not a learned state source")
    check_filter_asked(option, source, noise)
    check_own_filter_asked(option)
    if option["filter.fuse_odometry"] and not (noise is not None or learned):
        raise SafeRaceError("--fuse-odometry fuses a noisy or learned --state-source")
    samples = args.samples
    if samples is None:
        samples = MC_SAMPLES if learned else NOISY_SAMPLES
    config = config_from_args(
        FilterConfig(),
        args,
        prefix="filter.",
        state_noise=None if noise is None else tuple(noise),
        samples=samples,
        state_source=source if learned else None,
    )
    return config


def default_state_source(args: argparse.Namespace) -> str:
    """The state source of a command line that names none: its ``perceived_default`` where
    it asks for a filter with no noise and no monitor's source, else the truth."""
    option = vars(args)
    asked = option["filter.kind"] != "none" and args.state_noise is None
    if asked and not option.get("monitor_state_source"):
        return option.get("perceived_default", "oracle")
    return "oracle"


def check_filter_asked(option: dict, source: str, noise: object) -> None:
    """Raise where a filter's options are given without a filter."""
    needs_filter = (
        noise is not None,
        not option["filter.probabilistic"],
        source != "oracle",
        option["filter.map_curvature"],
        option["filter.spread_scale"] is not None,
        option["filter.fuse_odometry"],
        option["filter.opponent_noise_m"] != 0.0,
    )
    if option["filter.kind"] == "none" and any(needs_filter):
        raise SafeRaceError(
            "--state-source, --state-noise, --deterministic, --map-curvature, --spread-scale, "
            "--fuse-odometry and --opponent-noise need --filter cbf"
        )


def check_own_filter_asked(option: dict) -> None:
    """Raise where our filters' own settings are given with a filter of the user's."""
    from saferace.eval.filter_config import FilterConfig, users_filter

    ours = {
        "--filter-gains": option["filter.gains"] != AUTO,
        "--filter-model": option["filter.model"] != AUTO,
        "--filter-uncertainty": option["filter.uncertainty"] != AUTO,
        "--eta": option["filter.eta"] != FilterConfig.eta,
        "--deterministic": not option["filter.probabilistic"],
    }
    asked = [flag for flag, given in ours.items() if given]
    if users_filter(option["filter.kind"]) and asked:
        raise SafeRaceError(
            f"{', '.join(asked)}: our filters' settings, not of {option['filter.kind']}"
        )


def built_filter_config(args: argparse.Namespace):
    """:func:`filter_config`, with the generic perception model it names built first
    (:func:`ensure_generic_model`)."""
    config = filter_config(args)
    ensure_generic_model(config.state_source, getattr(args, "workers", 1))
    return config


def ensure_generic_model(source: str | None, workers: int = 1) -> None:
    """Build the generic perception model ``source`` names where it is not built yet (once,
    in this process, before any worker needs it). Only that source imports the learning
    package: PyTorch costs a command that needs none seconds to start."""
    if (source or "").partition(":")[0] == GENERIC_SOURCE:
        from saferace.learning.perception import ensure_perception_model

        ensure_perception_model(source, workers)


def is_perceived(source: str) -> bool:
    """Whether ``source`` names a perception: a state network (``learned:CHECKPOINT`` or
    ``generic[:RECIPE]``, an unknown recipe raises) or a user's perception method
    (``MODULE:FACTORY``, :mod:`saferace.safety.uncertainty.perception`)."""
    kind, _, argument = source.partition(":")
    if kind not in (GENERIC_SOURCE, "learned") and kind and argument:
        return True
    if kind == GENERIC_SOURCE:
        if argument and argument not in PERCEPTION_RECIPES:
            raise SafeRaceError(
                f"no perception recipe {argument!r}: use generic or generic:RECIPE with "
                f"RECIPE one of {', '.join(PERCEPTION_RECIPES)}"
            )
        return True
    return kind == "learned" and bool(argument)


def add_track_arguments(parser: argparse.ArgumentParser) -> None:
    """A track to load and report on: the positional track and how to load it."""
    parser.add_argument("track", type=values.track, help=TRACK_HELP)
    parser.add_argument(
        "--car-width-m", type=values.positive, default=None, help="car width (default 0.30)"
    )
    parser.add_argument(
        "--margin-m", type=values.non_negative, default=None, help="extra clearance (default 0.10)"
    )
    parser.add_argument("--plot", type=Path, help="draw the track, both lines and speeds to a PNG")
    parser.add_argument(
        "--strict",
        action="store_true",
        help="refuse a track whose turns are tighter than its half width instead of narrowing it",
    )
    parser.add_argument(
        "--smooth-rms-m",
        type=values.positive,
        help="smooth a noisy centre line: a spline that moves its points by this RMS distance "
        "(e.g. 0.05)",
    )
    parser.add_argument(
        "--smooth-keeps",
        choices=SMOOTHING_KEEPS,
        help="what a smoothed lane keeps: the given widths (default: its boundaries move with the "
        "centre line, as the F1TENTH collection's lanes) or the given boundaries (measured edges)",
    )


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", help=f"where the networks run: {DEVICE_HELP} (default: auto)")


def add_slack_argument(parser: argparse.ArgumentParser, where: str) -> None:
    """``--filter-slack`` for a command that runs many filters (``where``: which of them)."""
    parser.add_argument(
        "--filter-slack",
        default=SQUARED_SLACK,
        choices=SLACK_PENALTIES,
        help=f"the filter QP's penalty on its slacks in {where}: squared (the paper's) or the "
        "exact l1",
    )


def add_parallel_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("parallel runs")
    group.add_argument("--workers", type=values.count, default=1, help="runs at once, in processes")
    group.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="one Ray task per run: on a Ray cluster at ADDRESS, or a local Ray instance "
        "(needs saferace[ray])",
    )


def add_num_envs_argument(parser: argparse.ArgumentParser) -> None:
    """``--num-envs``: episodes driven at once (gymnasium's vector API in lockstep for
    learned drivers)."""
    parser.add_argument(
        "--num-envs",
        type=values.count,
        default=1,
        metavar="N",
        help="episodes driven at once in worker processes (as many as cores): a learned "
        "driver's in lockstep, its network asked once per step for all of them; in a "
        "collection, the expert's and scripted drivers' each driven through in a worker (the "
        "frames of one by one: bit for bit with the expert and scripted drivers, to float "
        "rounding with a learned one)",
    )


def add_randomize_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--randomize",
        default="none",
        choices=RANDOMIZATION_PRESETS,
        metavar="PRESET",
        help="visual domain randomisation: none, mild or strong (a look per episode seed)",
    )
