"""Griffe extension: SafeRace's plain-text docstrings made to render as Markdown.

The docstrings are plain text with ``rst`` literals and roles such as
``:class:`~saferace.eval.filter_config.FilterConfig```, and lists that start right after a
line of text. Markdown would print the role's name and run such a list into the line
above. This turns a role into a code span of its target (the last part with ``~``) and
puts a blank line before a list that follows text. The docstrings themselves are not
changed.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:class|func|meth|attr|mod|data|obj|exc|const):`(~?)([^`]+)`")
LIST_ITEM = re.compile(r"^\s*(?:[-*+]|\d+[.)])\s+\S")


def _code(match: re.Match[str]) -> str:
    target = match.group(2)
    return f"``{target.rsplit('.', 1)[-1] if match.group(1) else target}``"


def markdown_docstring(text: str) -> str:
    """``text`` with roles as code spans and a blank line before each list."""
    lines: list[str] = []
    in_list = False
    for line in ROLE.sub(_code, text).split("\n"):
        if not line.strip():
            in_list = False
        elif LIST_ITEM.match(line):
            if not in_list and lines and lines[-1].strip():
                lines.append("")
            in_list = True
        lines.append(line)
    return "\n".join(lines)


class SphinxRoles(griffe.Extension):
    def on_object(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = markdown_docstring(obj.docstring.value)
