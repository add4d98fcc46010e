"""The house's one-way data flow, read from the imports (ast), and a numpy-only core."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "rlu"

# package part -> parts of rlu it must not import
FORBIDDEN = {
    "data": ("rlu.agents", "rlu.envs", "rlu.evaluation", "rlu.train", "rlu.generate"),
    "envs": ("rlu.agents", "rlu.data", "rlu.evaluation", "rlu.train", "rlu.generate"),
    "agents": ("rlu.data", "rlu.envs", "rlu.evaluation", "rlu.train", "rlu.generate", "rlu.tasks"),
    "evaluation": ("rlu.agents", "rlu.train", "rlu.generate"),
    "types.py": ("rlu.",),
    "tasks.py": ("rlu.data", "rlu.envs", "rlu.agents", "rlu.evaluation"),
}


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def test_data_flows_one_way():
    problems = []
    for part, banned in FORBIDDEN.items():
        files = [PKG / part] if part.endswith(".py") else sorted((PKG / part).rglob("*.py"))
        for f in files:
            if not f.exists():
                continue
            for name in _imports(f):
                if any(
                    name == b.rstrip(".") or name.startswith(b.rstrip(".") + ".") for b in banned
                ):
                    problems.append(f"{f.relative_to(ROOT)} imports {name}")
    assert not problems, "\n".join(problems)


def test_core_imports_numpy_only():
    code = (
        "import sys, rlu, rlu.tasks, rlu.data, rlu.data.validate, rlu.data.d4rl, rlu.cli;"
        "rlu.cli.build_parser();"
        "heavy = [m for m in ('torch', 'jax', 'mujoco', 'dm_control', 'ale_py', 'gymnasium', "
        "'ray', 'tensorflow', 'h5py') if m in sys.modules];"
        "print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"core import pulled in: {out.stdout}"
