"""Command-line options generated from config dataclasses, and configs built back from them.

Every field of a config made with :func:`saferace.config.setting` becomes an option: its
flag (``--field-name`` unless the field names another), its type from the annotation
(``bool`` a switch, ``tuple[float, float]`` two values, ``tuple[int, ...]`` one or more),
its default from the config instance the command starts from (``auto`` where the field
declares it: the config settles it from the other options), and its help from the field.
A config's :class:`~saferace.errors.ConfigError` is shown with the option in place of the
field's name.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from typing import Any

from saferace.cli.values import CheckedNumber, Distinct
from saferace.config import Bounds
from saferace.names import AUTO

#: Where each command keeps, in its parsed arguments, the flags of its config fields.
FLAGS_KEY = "config_flags"


def add_config_options(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    config: Any,
    prefix: str = "",
    exclude: tuple[str, ...] = (),
    command: argparse.ArgumentParser | None = None,
) -> None:
    """Add an option per field of the dataclass instance ``config`` (its values are the
    defaults) to ``parser``, stored as ``PREFIX + field``; nested configs and ``exclude``d
    fields are left out. ``command`` is the subcommand's parser when ``parser`` is a group."""
    hints = typing.get_type_hints(type(config))
    flags = {}
    for field in dataclasses.fields(config):
        if field.name in exclude or "help" not in field.metadata:
            continue
        flag = field.metadata["flag"] or "--" + field.name.replace("_", "-")
        default = getattr(config, field.name)
        if field.default == AUTO:  # settled when the config is made, from the other options
            default = AUTO
        kwargs = _argument(hints[field.name], default, field.metadata.get("bounds"))
        for key in ("choices", "metavar"):
            if field.metadata[key] is not None:
                kwargs[key] = field.metadata[key]
        if "action" not in kwargs and "metavar" not in kwargs and "choices" not in kwargs:
            kwargs["metavar"] = field.name.upper()
        if field.name == "seeds":  # a seed twice runs one episode twice, counted as two
            kwargs["action"] = Distinct
        parser.add_argument(flag, dest=prefix + field.name, help=field.metadata["help"], **kwargs)
        flags[field.name] = flag
    target = command if command is not None else parser
    assert isinstance(target, argparse.ArgumentParser)
    target.set_defaults(**{FLAGS_KEY: {**(target.get_default(FLAGS_KEY) or {}), **flags}})


def config_from_args(config: Any, args: argparse.Namespace, prefix: str = "", **values: Any) -> Any:
    """``config`` with every field that :func:`add_config_options` added taken from
    ``args`` (lists as tuples), and ``values`` on top."""
    parsed = vars(args)
    for field in dataclasses.fields(config):
        if prefix + field.name in parsed and field.name not in values:
            value = parsed[prefix + field.name]
            values[field.name] = tuple(value) if isinstance(value, list) else value
    return dataclasses.replace(config, **values)


def _argument(hint: Any, default: Any, bounds: Bounds | None) -> dict[str, Any]:
    """argparse keywords for a field annotated ``hint`` with ``default`` (its numbers
    checked against ``bounds`` where it has them)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        (hint,) = (arg for arg in typing.get_args(hint) if arg is not type(None))
    if hint is bool:
        return {"action": "store_false" if default else "store_true", "default": default}
    if typing.get_origin(hint) is tuple:
        items = typing.get_args(hint)
        nargs: int | str = "+" if items[-1] is Ellipsis else len(items)
        listed = None if default is None else list(default)
        return {"type": _checked(items[0], bounds), "nargs": nargs, "default": listed}
    return {"type": _checked(hint, bounds), "default": default}


def _checked(number_type: Any, bounds: Bounds | None) -> Any:
    return number_type if bounds is None else CheckedNumber(number_type, bounds)
