"""Domain names live in the domain registry: outside ``rlu/domains/`` (each domain's folder, its
env and release families with it), no string in rlu's code is a domain's name or starts with one
(``"atari"``, ``"rwrl/..."``), docstrings aside. The strings left are counted per file below with
what they name; a new one fails this test (read the domain's entry in ``rlu.domains`` instead)."""

from __future__ import annotations

import ast
import re
from collections import Counter
from pathlib import Path

from rlu.domains import DOMAINS

ROOT = Path(__file__).resolve().parents[2]

# file -> (strings allowed, why they remain)
LEFT = {
    # not a domain's name: the discrete configs' field of Nature-CNN settings, named `atari`
    # since the first discrete agent (renaming it would break saved configs and overrides such
    # as `atari.batch_size=32`)
    "rlu/agents/discrete_common.py": (1, "the discrete configs' `atari` settings field"),
}


PATTERN = re.compile("^({})(/|$)".format("|".join(map(re.escape, DOMAINS))))


def _count(source: str) -> int:
    """Strings of ``source`` that are a domain's name or start with one, docstrings aside."""
    tree = ast.parse(source)
    docstrings = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            first = node.body[0] if node.body else None
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                docstrings.add(id(first.value))
    return sum(
        1
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant)
        and isinstance(node.value, str)
        and id(node) not in docstrings
        and PATTERN.match(node.value)
    )


def _literals() -> Counter:
    counts: Counter = Counter()
    for path in sorted((ROOT / "rlu").rglob("*.py")):
        rel = path.relative_to(ROOT)
        if rel.parts[1] == "domains":
            continue
        n = _count(path.read_text())
        if n:
            counts[str(rel)] = n
    return counts


def test_no_new_domain_name_literals_outside_the_registry():
    counts = _literals()
    over = {f: n for f, n in counts.items() if n > LEFT.get(f, (0, ""))[0]}
    assert not over, (
        f"domain names written out in {over}: read the domain's entry in rlu.domains instead"
    )
    # the list shrinks as literals move: an entry above its file's count is stale
    stale = {f: (LEFT[f][0], counts.get(f, 0)) for f in LEFT if counts.get(f, 0) < LEFT[f][0]}
    assert not stale, f"lower these counts in LEFT (allowed, found): {stale}"
    assert sum(counts.values()) == sum(n for n, _ in LEFT.values())


def test_the_count_sees_a_literal():
    """The counter finds a domain's name and a task id in code, not in a docstring or in a
    longer word."""
    src = 'def f(t):\n    """atari"""\n    return t.domain == "atari" or t.id in ("rwrl/x", "a")\n'
    assert _count(src) == 2
