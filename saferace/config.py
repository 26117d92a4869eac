"""Config dataclass fields that describe themselves, so the command line can be generated.

A field made with :func:`setting` carries its help text (and optionally the flag, choices
and metavar the command line shows) in its metadata; ``saferace.cli.options`` turns every
such field of a config into an option with the field's default, so that a field added to a
config appears on the command line with no second copy. Import-free, like
:mod:`saferace.names`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import MISSING, field
from typing import Any


def setting(
    default: Any = MISSING,
    help: str = "",
    *,
    flag: str | None = None,
    choices: Sequence[str] | None = None,
    metavar: str | tuple[str, ...] | None = None,
    default_factory: Any = MISSING,
) -> Any:
    """A dataclass field with its command-line description.

    ``flag`` renames the option (default: ``--field-name``); for a boolean field that
    defaults to True it is the flag that turns it off (``--from-scratch`` for
    ``warm_start``).
    """
    metadata = {"help": help, "flag": flag, "choices": choices, "metavar": metavar}
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata=metadata)
    return field(default=default, metadata=metadata)
