"""The docs site's links land on pages it builds (``mkdocs build --strict`` passes a link
to a page it excludes, and the built link is dead), a measured figure in its prose says
where it was measured, the commands it quotes use options and values the parser takes, and
the command line's help names what its errors accept."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from saferace.cli import build_parser
from saferace.cli.values import CheckedNumber
from saferace.envs.traffic import OPPONENT_POLICIES
from saferace.names import OPPONENTS_HELP

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
#: mkdocs.yml's ``exclude_docs``: folders whose files are snippets or build code, not pages.
EXCLUDED = ("hooks", "results/*")
LINK = re.compile(r"\]\(([^)#\s]+\.md)(?:#[^)]*)?\)")


def excluded(path: Path) -> bool:
    relative = path.relative_to(DOCS)
    return any(relative.parent.match(pattern) for pattern in EXCLUDED)


PAGES = sorted(path for path in DOCS.rglob("*.md") if not excluded(path))


@pytest.mark.parametrize("page", PAGES, ids=lambda path: str(path.relative_to(DOCS)))
def test_every_link_of_a_page_lands_on_a_built_page(page: Path):
    for target in LINK.findall(page.read_text()):
        if "://" in target:
            continue
        path = (page.parent / target).resolve()
        assert path.is_file(), f"{page.name} links {target}, which is not there"
        assert not excluded(path), f"{page.name} links {target}, a snippet the site leaves out"


def test_the_link_check_sees_an_excluded_snippet():
    snippet = DOCS / "results" / "speed" / "filter.md"
    assert snippet.is_file() and excluded(snippet) and not excluded(DOCS / "results" / "speed.md")


def test_the_opponents_help_names_every_policy_its_error_accepts():
    named = OPPONENTS_HELP.split(":", 1)[1]
    assert all(re.search(rf"\b{re.escape(policy)}\b", named) for policy in OPPONENT_POLICIES)


#: A percentage next to what a run measures: "covered the truth on 76%", "lapped 11% slower".
MEASURED = r"(coverage|covered|lapped|slower|faster|alarms|completion|completed)"
MEASURED_FIGURE = re.compile(
    rf"(?<![\w.])\d+(?:\.\d+)?(?:-\d+(?:\.\d+)?)?\s?%[^.;:]{{0,60}}?\b{MEASURED}\b"
    rf"|\b{MEASURED}\b[^.;:]{{0,60}}?(?<![\w.])\d+(?:\.\d+)?\s?%",
    re.IGNORECASE,
)
#: Where a figure may come from: a stamped results page or the changelog (linked), or the
#: test or benchmark that measures it (named).
SOURCE = re.compile(r"\]\([^)]*(results/|changelog\.md)[^)]*\)|`(tests|benchmarks)/[\w/]+\.py`")


def unsourced_figures(text: str) -> list[str]:
    """The paragraphs of ``text`` (tables and includes aside) that quote a measured figure
    without saying where it comes from. A results page's own includes are its source."""
    if "--8<--" in text:
        return []
    return [
        " ".join(paragraph.split())[:120]
        for paragraph in re.split(r"\n\s*\n", text)
        if not paragraph.lstrip().startswith(("|", "```"))
        and MEASURED_FIGURE.search(paragraph)
        and not SOURCE.search(paragraph)
    ]


@pytest.mark.parametrize(
    "page",
    [page for page in PAGES if page.name != "changelog.md"],  # the changelog is the source
    ids=lambda path: str(path.relative_to(DOCS)),
)
def test_a_measured_figure_in_the_docs_says_where_it_was_measured(page: Path):
    """``uncertainty.md`` quoted 92%, 73% and 85% coverage with no stamped page behind
    them. Quote from an include (``--8<--``), or link the page or changelog entry."""
    assert unsourced_figures(page.read_text()) == []


def test_the_figure_check_tells_a_sourced_figure_from_a_bare_one():
    bare = "On `oval` the expert's interval covered the truth on 92% of steps."
    assert unsourced_figures(bare) == [bare]
    assert unsourced_figures(bare + " ([results](results/uncertainty.md))") == []
    assert unsourced_figures("Lapped 11% slower (`benchmarks/overtaking.py`).") == []
    assert unsourced_figures("A stretch at 55-70% of the lap is held out.") == []
    assert unsourced_figures('Prose, 92% covered.\n\n--8<-- "results/x.md"') == []


PARSER = build_parser()
GLOBAL_FLAGS = {flag for action in PARSER._actions for flag in action.option_strings}
COMMANDS = next(a for a in PARSER._actions if isinstance(a, argparse._SubParsersAction)).choices
#: ``saferace COMMAND`` and what follows it on the line (a line continued with a backslash
#: joined first), up to the end of a code span or a table cell.
QUOTED_COMMAND = re.compile(r"saferace ([a-z][a-z-]*)((?:[ \t]+[^\s`|]+)*)")
NUMBER = re.compile(r"^-?[\d.]+(?:e[+-]?\d+)?$")


def quoted_commands(text: str) -> list[tuple[str, list[str]]]:
    """Every ``saferace COMMAND ...`` in ``text`` that names a command: its tokens."""
    joined = text.replace("\\\n", " ")
    return [
        (match.group(1), match.group(2).split())
        for match in QUOTED_COMMAND.finditer(joined)
        if match.group(1) in COMMANDS
    ]


def disagreements(command: str, tokens: list[str]) -> list[str]:
    """The options of a quoted ``command`` its parser does not know, and the numbers it
    gives a numeric option that the option refuses (its range, its largest value)."""
    actions = {
        flag: action for action in COMMANDS[command]._actions for flag in action.option_strings
    }
    found = []
    for at, token in enumerate(tokens):
        flag = token.strip("[]()").split("=")[0]
        if flag.startswith("--") and flag not in actions and flag not in GLOBAL_FLAGS:
            found.append(f"saferace {command} has no option {flag}")
        action = actions.get(flag)
        if action is None or not isinstance(action.type, CheckedNumber):
            continue
        for value in tokens[at + 1 :]:
            if not NUMBER.match(value):
                break
            try:
                action.type(value)
            except argparse.ArgumentTypeError as error:
                found.append(f"saferace {command} {flag} {value}: {error}")
    return found


DOCUMENTS = [*PAGES, ROOT / "README.md"]


@pytest.mark.parametrize("page", DOCUMENTS, ids=lambda path: path.name)
def test_the_commands_the_docs_quote_use_options_and_values_the_parser_takes(page: Path):
    """``safety-filter.md`` quoted ``--random-tracks 4242 9137``, which a cap on the option
    (made for a count, not a seed) refused."""
    found = [
        problem
        for quoted in quoted_commands(page.read_text())
        for problem in disagreements(*quoted)
    ]
    assert found == []


def test_the_command_check_sees_an_unknown_option_and_a_value_out_of_range():
    quoted = quoted_commands("Run `saferace eval --agent expert --lapz 2 --max-seconds -5`.")
    assert quoted == [("eval", ["--agent", "expert", "--lapz", "2", "--max-seconds", "-5"])]
    found = disagreements(*quoted[0])
    assert len(found) == 2 and "--lapz" in found[0] and "--max-seconds -5" in found[1]
    assert (
        len([command for page in DOCUMENTS for command in quoted_commands(page.read_text())]) > 100
    )
