"""MkDocs hook: the command reference, rendered from ``saferace.cli.build_parser()``.

``docs/reference/commands.md`` holds a pair of markers; at build time this hook replaces
them, and the note between them for readers of the raw page (on GitHub, where no hook
runs), with every subcommand's usage, options (flag, default, help) and epilog examples,
read from the parser the ``saferace`` console script runs. The page therefore cannot drift
from the code: a renamed option or a new command shows up on the next ``make docs``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path

MARKER = "<!-- saferace-commands -->"
END_MARKER = "<!-- /saferace-commands -->"
PAGE = "reference/commands.md"
#: Usage lines are wrapped at this width whatever the terminal building the docs is.
USAGE_WIDTH = "80"


def on_page_markdown(markdown: str, page, config, files) -> str:
    if page.file.src_uri != PAGE:
        return markdown
    return with_commands(markdown, render_commands())


def with_commands(markdown: str, reference: str) -> str:
    """``markdown`` with its markers, and what lies between them, replaced by ``reference``."""
    head, start, rest = markdown.partition(MARKER)
    _, end, tail = rest.partition(END_MARKER)
    if not (start and end):
        raise ValueError(
            f"{PAGE} lost its markers {MARKER!r} and {END_MARKER!r}: the command reference "
            "has no place"
        )
    return f'{head}<div class="saferace-commands" markdown>\n\n{reference}\n\n</div>{tail}'


def render_commands() -> str:
    """The command reference as markdown."""
    root = str(Path(__file__).resolve().parents[2])
    if root not in sys.path:
        sys.path.insert(0, root)
    os.environ["COLUMNS"] = USAGE_WIDTH  # argparse's formatter reads it
    cli = importlib.import_module("saferace.cli")
    parser = cli.build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    summaries = {action.dest: action.help or "" for action in subparsers._choices_actions}

    families: dict[str, list[str]] = {name: [] for name in cli.COMMAND_MODULES}
    for name, sub in subparsers.choices.items():
        module = sub.get_default("command").__module__.rsplit(".", 1)[-1]
        families.setdefault(module, []).append(name)

    out = [
        "## `saferace`",
        "",
        _code(parser.format_usage()),
        _group_tables(parser, skip_positionals=True),
        "| command | what it does |",
        "|---|---|",
    ]
    for family in families.values():
        out += [f"| [`{name}`](#{name}) | {_cell(summaries[name])} |" for name in family]
    out.append("")
    for module, names in families.items():
        if not names:
            continue
        doc = importlib.import_module(f"saferace.cli.{module}").__doc__ or module
        out += [f"## {_family_title(module)}", "", _cell(doc.strip().split("\n\n")[0]), ""]
        for name in names:
            out += _command(name, subparsers.choices[name], summaries[name])
    return "\n".join(out)


def _command(name: str, parser: argparse.ArgumentParser, summary: str) -> list[str]:
    sentence = _cell(summary)
    lines = [f"### saferace {name} {{#{name}}}", "", sentence[:1].upper() + sentence[1:] + ".", ""]
    if parser.description:
        lines += [parser.description, ""]
    lines += [_code(parser.format_usage()), _group_tables(parser)]
    if parser.epilog:
        lines += [_epilog(parser.epilog)]
    return lines


def _group_tables(parser: argparse.ArgumentParser, skip_positionals: bool = False) -> str:
    formatter = parser._get_formatter()
    plain = argparse.HelpFormatter(parser.prog)  # the help without "(default: ...)"
    blocks = []
    for group in parser._action_groups:
        actions = [
            a
            for a in group._group_actions
            if a.help is not argparse.SUPPRESS
            and not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))
        ]
        if not actions or (skip_positionals and group.title == "positional arguments"):
            continue
        rows = ["| argument | default | description |", "|---|---|---|"]
        for action in actions:
            help_text = plain._expand_help(action) if action.help else ""
            if action.choices is not None and not isinstance(action.choices, dict):
                # the choices in the description, not in the flag: the column stays narrow
                invocation = ", ".join(action.option_strings) or action.dest
                listed = ", ".join(f"`{choice}`" for choice in action.choices)
                help_text = f"{help_text}; one of {listed}" if help_text else f"One of {listed}."
            else:
                invocation = formatter._format_action_invocation(action)
            rows.append(
                f"| `{_cell(invocation, code=True)}` | {_default(action)} | {_cell(help_text)} |"
            )
        blocks.append(f"**{group.title}**\n\n" + "\n".join(rows) + "\n")
    return "\n".join(blocks)


def _default(action: argparse.Action) -> str:
    """The default as ``saferace COMMAND --help`` shows it (none for unset values and switches)."""
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
        # a switch: whether what its flag says is in effect without the flag
        return "on" if action.default == action.const else "off"
    if action.required or action.default in (None, False, argparse.SUPPRESS):
        return ""
    return f"`{_cell(str(action.default), code=True)}`"


def _epilog(epilog: str) -> str:
    head, _, body = epilog.partition("\n")
    if head.strip().rstrip(":") == "examples" and body:
        lines = [line.strip() for line in body.splitlines()]
        return "**examples**\n\n```text\n" + "\n".join(lines) + "\n```\n"
    return _code(epilog)


def _family_title(module: str) -> str:
    return {"sysid": "System identification"}.get(module, module.capitalize())


def _code(text: str) -> str:
    return "```text\n" + text.strip("\n") + "\n```\n"


def _cell(text: str, code: bool = False) -> str:
    """Text for one markdown table cell: one line, pipes escaped."""
    text = " ".join(text.split())
    return text if code else text.replace("|", "\\|").replace("<", "&lt;")
