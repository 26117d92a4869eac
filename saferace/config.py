"""Config dataclass fields that describe themselves, so the command line can be generated.

A field made with :func:`setting` carries its help text (and optionally the flag, choices
and metavar the command line shows) in its metadata; ``saferace.cli.options`` turns every
such field of a config into an option with the field's default, so that a field added to a
config appears on the command line with no second copy. It imports nothing of SafeRace but
its errors, like :mod:`saferace.names`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import MISSING, dataclass, field, fields
from typing import Any

from saferace.errors import ConfigError


def setting(
    default: Any = MISSING,
    help: str = "",
    *,
    flag: str | None = None,
    choices: Sequence[str] | None = None,
    metavar: str | tuple[str, ...] | None = None,
    default_factory: Any = MISSING,
    bounds: Bounds | None = None,
) -> Any:
    """A dataclass field with its command-line description.

    ``flag`` renames the option (default: ``--field-name``); for a boolean field that
    defaults to True it is the flag that turns it off (``--from-scratch`` for
    ``warm_start``). ``bounds`` is the range of a number (of each number of a tuple): the
    command line refuses a value outside it where it parses it, and the config's
    ``__post_init__`` through :func:`check_bounds`.
    """
    metadata = {
        "help": help, "flag": flag, "choices": choices, "metavar": metavar, "bounds": bounds,
    }  # fmt: skip
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata=metadata)
    return field(default=default, metadata=metadata)


@dataclass(frozen=True)
class Bounds:
    """The range of a number: at least ``minimum`` (or above ``above``), at most
    ``maximum`` (or below ``below``); each end is open where it is None."""

    minimum: float | None = None
    maximum: float | None = None
    above: float | None = None
    below: float | None = None

    def problem(self, value: float) -> str | None:
        """What is wrong with ``value`` (``must ...``), or None if it is in range."""
        if math.isnan(value):
            return f"must be a number, got {value}"
        for limit, wrong, words in (
            (self.minimum, lambda x, m: x < m, "at least"),
            (self.above, lambda x, m: x <= m, "above"),
            (self.maximum, lambda x, m: x > m, "at most"),
            (self.below, lambda x, m: x >= m, "below"),
        ):
            if limit is not None and wrong(value, limit):
                return f"must be {words} {readable(limit)}, got {readable(value)}"
        return None


def readable(number: float) -> str:
    """``number`` as a person writes it: 86,400 and 4,294,967,295, not 4.29497e+09."""
    if math.isfinite(number) and number == int(number) and abs(number) < 1e18:
        return f"{int(number):,}"
    return f"{number:g}"


#: Ranges that many settings share.
COUNT = Bounds(minimum=1)
NON_NEGATIVE = Bounds(minimum=0)
POSITIVE = Bounds(above=0)
SHARE = Bounds(above=0, below=1)
#: An onboard image's height and width (pixels), as the tasks take them.
IMAGE_SIZE = Bounds(minimum=8, maximum=480)


def check_bounds(config: Any) -> None:
    """Raise the :class:`~saferace.errors.ConfigError` of the first field of the dataclass
    instance ``config`` whose number (or a number of whose tuple) is outside its bounds."""
    for item in fields(config):
        bounds: Bounds | None = item.metadata.get("bounds")
        value = getattr(config, item.name)
        if bounds is None or value is None:
            continue
        for number in value if isinstance(value, tuple | list) else (value,):
            if (problem := bounds.problem(float(number))) is not None:
                raise ConfigError(item.name, problem)
