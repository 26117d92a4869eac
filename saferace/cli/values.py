"""Argument types that check a number where it is parsed: a bad value is refused in one
line that names its option, before any work starts."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from saferace.config import COUNT, IMAGE_SIZE, NON_NEGATIVE, POSITIVE, SHARE, Bounds
from saferace.names import VIDEO_SUFFIXES
from saferace.track import builtin_track_names


class CheckedNumber:
    """An argparse ``type``: ``number_type`` of the text, within ``bounds``."""

    def __init__(self, number_type: Callable[[str], float], bounds: Bounds) -> None:
        self.number_type, self.bounds = number_type, bounds
        self.__name__ = getattr(number_type, "__name__", "number")  # argparse names it so

    def __call__(self, text: str) -> float:
        try:
            value = self.number_type(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"must be {'a whole number' if self.number_type is int else 'a number'}, "
                f"got {text!r}"
            ) from None
        problem = self.bounds.problem(float(value))
        if problem is not None:
            raise argparse.ArgumentTypeError(problem)
        return value


#: The checked types of the command line's plain options.
count = CheckedNumber(int, COUNT)
samples = CheckedNumber(int, Bounds(minimum=2))  # a spread needs two
seed = CheckedNumber(int, NON_NEGATIVE)
image_size = CheckedNumber(int, IMAGE_SIZE)
positive = CheckedNumber(float, POSITIVE)
non_negative = CheckedNumber(float, NON_NEGATIVE)
share = CheckedNumber(float, SHARE)


def existing(text: str) -> Path:
    """A file or folder that exists (an input)."""
    path = Path(text)
    if not path.exists():
        raise argparse.ArgumentTypeError(f"no such file or folder: {text}")
    return path


def video_file(text: str) -> Path:
    """Where a video goes: a path ending in one of :data:`~saferace.names.VIDEO_SUFFIXES`."""
    path = Path(text)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise argparse.ArgumentTypeError(
            f"{text}: a video is written as {' or '.join(VIDEO_SUFFIXES)} (H.264 or VP8)"
        )
    return path


def track(text: str) -> str:
    """A built-in track's name or the path of a track CSV file."""
    if text in builtin_track_names() or Path(text).is_file():
        return text
    raise argparse.ArgumentTypeError(
        f"{text!r} is neither a built-in track ({', '.join(builtin_track_names())}) nor a "
        "track CSV file"
    )


def fault(text: str) -> str:
    """A sensor or actuator fault, ``NAME[:KEY=VALUE,...]`` (:mod:`saferace.faults`)."""
    from saferace.faults.spec import FaultError, parse_fault

    try:
        parse_fault(text)
    except FaultError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def labelled_folder(text: str) -> tuple[str, Path]:
    """``LABEL=FOLDER`` with a folder that exists."""
    label, _, folder = text.partition("=")
    if not label or not folder:
        raise argparse.ArgumentTypeError(
            f"name each as LABEL=FOLDER, e.g. ensemble=results/ens, got {text!r}"
        )
    return label, existing(folder)


class Distinct(argparse.Action):
    """An ``nargs="+"`` option's ``action`` that refuses a value given twice (``--seeds 0 0``
    would run the same episode twice and count it as two)."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        given: object,
        option_string: str | None = None,
    ) -> None:
        items = list(given) if isinstance(given, list) else [given]
        repeated = next((item for index, item in enumerate(items) if item in items[:index]), None)
        if repeated is not None:
            parser.error(f"argument {option_string}: {repeated} is given twice; give each once")
        setattr(namespace, self.dest, items)
