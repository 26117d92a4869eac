"""The docs site's links land on pages it builds (``mkdocs build --strict`` passes a link
to a page it excludes, and the built link is dead), and the command line's help names
what its errors accept."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from saferace.envs.traffic import OPPONENT_POLICIES
from saferace.names import OPPONENTS_HELP

DOCS = Path(__file__).resolve().parents[1] / "docs"
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
