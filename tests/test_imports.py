"""The house's one-way data flow, read from the imports (ast), and a numpy-only core."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "rlu"

# package part (a folder or a file under rlu/) -> parts of rlu it must not import. The layers,
# lowest first: types, system, files, seeds, devices; codecs (the release's record codecs) and
# segments (the in-memory data model); domains (each domain's tasks, env and release families,
# and the kits they are built of); tasks; data, envs; agents; evaluation; training (the run
# lifecycle); report; generate; commands and the CLI.
ABOVE_TRAINING = ("rlu.report", "rlu.generate", "rlu.commands", "rlu.cli")
# the layers above the low modules (types, system, files, seeds, devices, tasks, workers)
LOW = ("rlu.data", "rlu.envs", "rlu.agents", "rlu.evaluation", "rlu.training", *ABOVE_TRAINING)
# what the release's record codecs and the data model may not import: anything but types/system
BELOW_DOMAINS = (
    "rlu.files",
    "rlu.seeds",
    "rlu.devices",
    "rlu.workers",
    "rlu.progress",
    "rlu.locks",
    "rlu.domains",
    "rlu.tasks",
    *LOW,
)
FORBIDDEN = {
    "codecs": (*BELOW_DOMAINS, "rlu.segments"),
    "segments.py": (*BELOW_DOMAINS, "rlu.codecs"),
    # a domain's folder and the kits of rlu/domains sit below the task registry and every part
    # that reads the domains (data, envs, ...): they import none of them
    "domains": ("rlu.tasks", *LOW),
    "data": ("rlu.agents", "rlu.envs", "rlu.evaluation", "rlu.training", *ABOVE_TRAINING),
    "envs": ("rlu.agents", "rlu.data", "rlu.evaluation", "rlu.training", *ABOVE_TRAINING),
    "agents": ("rlu.data", "rlu.envs", "rlu.evaluation", "rlu.training", "rlu.tasks",
               *ABOVE_TRAINING),
    "evaluation": ("rlu.agents", "rlu.training", *ABOVE_TRAINING),
    "training": ABOVE_TRAINING,
    "report": ("rlu.generate", "rlu.commands", "rlu.cli"),
    "generate": ("rlu.report", "rlu.commands", "rlu.cli"),
    "types.py": ("rlu.",),
    "system.py": ("rlu.",),
    "seeds.py": LOW,
    "devices.py": LOW,
    "tasks.py": LOW,
    "files.py": (*LOW, "rlu.devices"),
    "workers.py": LOW,
    # inside training: the run and sweep folders' files sit below the loop, its settings below
    # everything, rebuilding a finished run above the loop and beside the sweep
    "training/runs.py": ("rlu.training.train", "rlu.training.sweep", "rlu.training.restore",
                         "rlu.evaluation", "rlu.agents", "rlu.data", "rlu.envs"),
    "training/config.py": ("rlu.data", "rlu.envs", "rlu.agents", "rlu.evaluation",
                           "rlu.training.train", "rlu.training.runs", "rlu.training.sweep",
                           "rlu.training.restore"),
    "training/train.py": ("rlu.training.sweep", "rlu.training.restore"),
    "training/sweep.py": ("rlu.training.restore", "rlu.evaluation"),
    "training/restore.py": ("rlu.training.sweep",),
}  # fmt: skip


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


def _part(module: str) -> str | None:
    bits = module.split(".")
    if bits[0] != "rlu" or len(bits) == 1:
        return None
    return bits[1] if (PKG / bits[1]).is_dir() or (PKG / f"{bits[1]}.py").exists() else None


def test_no_circle_between_the_parts_of_the_house():
    """Every import between rlu's parts (data, envs, runs, train, ...), at module level or
    inside a function, points one way: the graph of parts has no cycle."""
    edges: dict[str, set[str]] = {}
    for f in PKG.rglob("*.py"):
        parts = f.relative_to(ROOT).with_suffix("").parts
        source = _part(".".join(p for p in parts if p != "__init__"))
        if source is None or source == "__main__":
            continue
        for name in _imports(f) | _imported_names(f):
            target = _part(name)
            if target is not None and target != source:
                edges.setdefault(source, set()).add(target)
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                raise AssertionError("import circle: " + " -> ".join([*path, node, nxt]))
            if nxt not in state:
                visit(nxt, [*path, node])
        state[node] = 2

    for node in sorted(edges):
        if node not in state:
            visit(node, [])


def _imported_names(path: Path) -> set[str]:
    """``from rlu.training import runs`` names the module rlu.training.runs."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.update(f"{node.module}.{a.name}" for a in node.names)
    return names


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


# file -> file imports that point back up inside a part, each with why it stays
BACK_UP = {
    # Minari's episode API as methods on the store's Dataset (ds.sample_episodes(5),
    # ds.recover_environment(), as on minari.MinariDataset); they are thin and hand on to
    # rlu.data.episodes, which sits above the store with the views and adapters it needs
    ("rlu.data.store.reader", "rlu.data.episodes"),
}


def _module(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(p for p in parts if p != "__init__")


MODULES = {_module(f) for f in PKG.rglob("*.py")}


def _runtime_imports(path: Path) -> set[str]:
    """The modules a file imports when it runs (module level or in a function, not under
    ``if TYPE_CHECKING:``); ``from rlu.training import runs`` imports rlu.training.runs."""
    names: set[str] = set()

    def walk(node: ast.AST) -> None:
        if isinstance(node, ast.If) and ast.unparse(node.test) in (
            "TYPE_CHECKING",
            "typing.TYPE_CHECKING",
        ):
            for child in node.orelse:
                walk(child)
            return
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:  # a module of the package, else a name the package defines
                sub = f"{node.module}.{a.name}"
                names.add(sub if sub in MODULES else node.module)
        for child in ast.iter_child_nodes(node):
            walk(child)

    walk(ast.parse(path.read_text()))
    return names


def _file_edges() -> dict[str, set[str]]:
    """Module -> the rlu modules it imports when it runs (``_runtime_imports``)."""
    edges: dict[str, set[str]] = {}
    for f in PKG.rglob("*.py"):
        source = _module(f)
        for name in _runtime_imports(f):
            if name in MODULES and name != source:
                edges.setdefault(source, set()).add(name)
    return edges


def _cycle(edges: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(node: str, path: list[str]) -> list[str] | None:
        state[node] = 1
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                return [*path, node, nxt]
            if nxt not in state and (found := visit(nxt, [*path, node])):
                return found
        state[node] = 2
        return None

    for node in sorted(edges):
        if node not in state and (found := visit(node, [])):
            return found
    return None


def test_no_circle_between_files_but_the_listed_ones():
    """Between rlu's files too the imports that run point one way, but for those in BACK_UP
    (each says why it stays); a package's __init__ counts as the package's module. Imports
    under ``if TYPE_CHECKING:`` name types for annotations only and are left out."""
    edges = _file_edges()
    for source, target in BACK_UP:
        assert target in edges.get(source, set()), f"{source} no longer imports {target}: drop it"
        edges[source].discard(target)
    cycle = _cycle(edges)
    assert cycle is None, "import circle: " + " -> ".join(cycle or [])


def test_the_file_circle_check_finds_a_circle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": {"c"}}) is None
