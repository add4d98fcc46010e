"""A Griffe extension for the rlu site (mkdocs.yml, mkdocstrings' ``extensions``): docstrings as
Markdown reads them.

rlu's docstrings are written for readers of the code, who see a list that starts right under
its lead-in line ("Deviations:" then "- ..."). Markdown needs a blank line there, or the items
run into one paragraph. This inserts it, in the text the site renders only; the code's
docstrings stay as written.
"""

from __future__ import annotations

import re
from typing import Any

from griffe import Extension

_ITEM = re.compile(r"( *)[-*] \S")


def blank_line_before_lists(text: str) -> str:
    """``text`` with a blank line between a paragraph line and a list item that follows it at
    the same indentation (less than 4 spaces: deeper lines are code blocks, left alone)."""
    lines = text.split("\n")
    out: list[str] = []
    for i, line in enumerate(lines):
        item = _ITEM.match(line)
        if item and i > 0:
            prev = lines[i - 1]
            indent = len(item.group(1))
            prev_indent = len(prev) - len(prev.lstrip(" "))
            if prev.strip() and indent < 4 and prev_indent == indent and not _ITEM.match(prev):
                out.append("")
        out.append(line)
    return "\n".join(out)


class MarkdownLists(Extension):
    """Runs :func:`blank_line_before_lists` on every docstring Griffe loads."""

    def on_instance(self, *, obj: Any, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = blank_line_before_lists(obj.docstring.value)
