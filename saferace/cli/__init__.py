"""SafeRace's command line: racing lines, driving and evaluation, the safety filter's table,
the learned driver and the paper's experiments.

Each command family is a module with ``register(commands)``; handlers import what they
run when they run, so ``saferace --help`` and every subcommand's ``--help`` stay fast (no
torch, no MuJoCo).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from typing import Any, NoReturn

from saferace.cli.maxima import cap_numbers
from saferace.cli.options import FLAGS_KEY
from saferace.errors import ConfigError, SafeRaceError

#: The exit status of a command stopped by Ctrl-C or SIGTERM (a shell's for SIGINT).
INTERRUPTED = 130
#: The command families, in the order ``saferace --help`` lists them.
COMMAND_MODULES = ("tracks", "driving", "safety", "learning", "experiments", "sysid")


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Shows an option's default in its help, unless it has none (None or off), and keeps
    the examples' line breaks."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default in (None, False) or isinstance(action, argparse._StoreFalseAction):
            return action.help
        return super()._get_help_string(action)


class _Parser(argparse.ArgumentParser):
    """Formats its help with :class:`HelpFormatter`, and refuses bad arguments in one line
    (``saferace eval: error: argument --laps: must be at least 1, got -1``) with exit
    status 2; ``--help`` shows the usage."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")

    def parse_args(self, args: Any = None, namespace: Any = None) -> argparse.Namespace:  # type: ignore[override]
        """As argparse's, with arguments no option takes refused by the command they
        followed (``saferace drive: error: unrecognized arguments: --out run``)."""
        parsed, extras = self.parse_known_args(args, namespace)
        if extras:
            commands = [a for a in self._actions if isinstance(a, argparse._SubParsersAction)]
            name = getattr(parsed, "command_name", None)
            command = commands[0].choices.get(name, self) if commands and name else self
            command.error(f"unrecognized arguments: {' '.join(extras)}")
        return parsed


def build_parser() -> argparse.ArgumentParser:
    """The ``saferace`` parser with every command (also what the docs' reference renders)."""
    parser = _Parser(prog="saferace", description=__doc__.split("\n\n")[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress")
    commands = parser.add_subparsers(
        dest="command_name",
        required=True,
        metavar="COMMAND",
        parser_class=_Parser,
    )
    for name in COMMAND_MODULES:
        importlib.import_module(f"saferace.cli.{name}").register(commands)
    cap_numbers(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``saferace`` console script."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s"
    )
    try:
        if getattr(args, "device", None) is not None:
            from saferace.learning.device import use_device

            use_device(args.device)  # for this process and the workers it starts
        return args.command(args)
    except ConfigError as exc:
        flag = (getattr(args, FLAGS_KEY, None) or {}).get(exc.field, exc.field)
        print(f"saferace {args.command_name}: error: {flag} {exc.problem}", file=sys.stderr)
        return 2
    except SafeRaceError as exc:  # named by its command, as argparse names a bad option's
        print(f"saferace {args.command_name}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C, or SIGTERM where workers run: no traceback
        print(f"saferace {args.command_name}: interrupted", file=sys.stderr)
        return INTERRUPTED


def example(*commands: str) -> str:
    """A subcommand's epilog: its examples."""
    return "examples:\n" + "\n".join(f"  {command}" for command in commands)
