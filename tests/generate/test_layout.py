"""generate/'s layout: the three recipes are peers over common modules (no cycle, no private
imports across modules)."""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[2] / "rlu" / "generate"
RECIPES = {"rlu.generate.recipe", "rlu.generate.policy", "rlu.generate.rwrl"}


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.module, [a.name for a in node.names]))
        elif isinstance(node, ast.Import):
            out += [(a.name, []) for a in node.names]
    return out


def test_recipes_are_peers_without_private_imports():
    problems = []
    for f in sorted(PKG.glob("*.py")):
        me = f"rlu.generate.{f.stem}"
        for module, names in _imports(f):
            if not module.startswith("rlu."):
                continue
            private = [n for n in names if n.startswith("_")]
            if private:
                problems.append(f"{f.name} imports private {private} from {module}")
            if me in RECIPES and module in RECIPES - {me}:
                problems.append(f"{f.name} imports the peer recipe {module}")
    assert not problems, "\n".join(problems)
