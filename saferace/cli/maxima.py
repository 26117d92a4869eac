"""The most each numeric option of the command line takes.

A value past it is a typo or days of work: ``eval --laps 1000000`` printed nothing for
minutes and kept every step in memory. Every numeric option has an entry here or a reason
it needs none (:data:`UNCAPPED`), and :func:`cap_numbers` puts the entries into the
parser, so a new option without one fails ``tests/test_cli_bad_options.py``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math

from saferace.cli.values import CheckedNumber

#: An option's largest value, with why. Counts of work are set a hundred times above what
#: the paper and the benchmark use; lengths and noises at what a 1/10 car could meet.
MAXIMA: dict[str, float] = {
    "--batch-size": 4096,  # frames per gradient step; the paper's 64
    "--beta-rampdown": 100,  # iterations
    "--car-width-m": 2.0,  # a 1/10 car is 0.30 m wide
    "--early-stop": 1000,  # epochs of patience
    "--ensemble-members": 32,  # networks trained for one driver
    "--episodes": 1000,  # episodes collected per iteration
    "--epochs": 1000,  # the paper's 30
    "--expert-perturb": 1.0,  # rad of steering noise: more than the 0.36 rad lock
    "--filter-from": 100,  # an iteration
    "--frames": 1000,  # Grad-CAM frames over a lap
    "--iterations": 100,  # DAgger iterations; the paper's 5
    "--laps": 1000,  # per run (drive and eval estimate the work instead: UNCAPPED)
    "--lr": 1.0,  # a learning rate
    "--margin-m": 2.0,  # clearance beyond the car
    "--max-seconds": 86400.0,  # a day of simulated time per episode
    "--max-train-steps": 10_000_000,  # gradient steps
    "--mc-samples": 1000,  # MC-dropout passes per frame
    "--min-train-steps": 10_000_000,
    "--num-envs": 256,  # episodes driven at once
    "--opponent-noise": 5.0,  # m of noise on an opponent's position
    "--packed-alpha": 16.0,  # times ResNet-18's width
    "--packed-gamma": 16,  # groups per member
    "--perturb": 1.0,  # rad of steering noise
    "--perturb-correlation-s": 60.0,  # s a push of the noise lasts
    "--random-tracks": 2**32 - 1,  # the seeds of the tracks drawn
    "--runs": 1000,  # runs replayed
    "--samples": 1000,  # state samples or MC passes per frame
    "--seconds": 86400.0,  # a day of simulated time per run
    "--seed": 2**32 - 1,  # numpy's and gymnasium's seeds are 32-bit
    "--seeds": 2**32 - 1,
    "--smooth-rms-m": 1.0,  # m a spline may move the centre line's points
    "--spread-scale": 100.0,  # times the calibrated spread
    "--state-noise": 10.0,  # m (and rad) of noise on the filter's state
}
#: Numeric options that take no entry, the commands where (all: None), and why.
UNCAPPED: dict[str, tuple[tuple[str, ...] | None, str]] = {
    "--laps": (
        ("drive", "eval"),
        "estimated up front: refused past an hour of driving without --yes",
    ),
    "--workers": (None, "capped at the machine's cores, with one line saying so"),
}


def upper_end(checked: CheckedNumber) -> float:
    """The largest value ``checked`` takes (inf: none)."""
    ends = (checked.bounds.maximum, checked.bounds.below)
    return min((end for end in ends if end is not None), default=math.inf)


def uncapped(command: str, flag: str) -> bool:
    """Whether ``flag`` of ``command`` takes no entry of :data:`MAXIMA` (:data:`UNCAPPED`)."""
    commands, _ = UNCAPPED.get(flag, ((), ""))
    return commands is None or command in commands


def cap_numbers(parser: argparse.ArgumentParser) -> None:
    """Give every numeric option of every command of ``parser`` its :data:`MAXIMA` entry,
    where its own range has no lower upper end."""
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for command, command_parser in commands.choices.items():
        for action in command_parser._actions:
            if not isinstance(action.type, CheckedNumber) or not action.option_strings:
                continue
            flag = action.option_strings[-1]
            maximum = MAXIMA.get(flag)
            if (
                maximum is not None
                and not uncapped(command, flag)
                and maximum < upper_end(action.type)
            ):
                bounds = dataclasses.replace(action.type.bounds, maximum=maximum)
                action.type = CheckedNumber(action.type.number_type, bounds)
