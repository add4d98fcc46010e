"""The API reference is complete: every public name (each module's ``__all__``, and the public
methods and properties of the classes among them) has a docstring and is on the built site.

"On the site" is read from the site itself: mkdocstrings lists every object it rendered in
``objects.inv`` (an object without a docstring is not rendered: ``show_if_no_docstring`` is off),
so a name missing there is missing from the pages, whatever the reason (no docstring, a
directive's ``members`` filter, a module without a page). The test command builds the site into
``build/site`` before pytest runs; this test reads that build when it is newer than every file
the site is made from, and builds the site into a temporary folder otherwise (a few seconds on a
quiet machine)."""

from __future__ import annotations

import ast
import importlib
import inspect
import os
import pkgutil
import subprocess
import sys
import zlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LEFT_OUT = ("rlu.__main__", "rlu.cli", "rlu.commands")  # the command line: on the CLI page


def public_names() -> dict[str, set[str]]:
    """Each public name as ``module.name`` (``module.Class.method`` for methods) -> the paths
    the site may document it under (where it is listed, where it is defined)."""
    import rlu

    names: dict[str, set[str]] = {}
    modules = ["rlu", *(m.name for m in pkgutil.walk_packages(rlu.__path__, "rlu."))]
    for name in modules:
        if name.startswith(LEFT_OUT):
            continue
        try:
            module = importlib.import_module(name)
        except ImportError as e:  # an extra is missing here: its names cannot be walked
            pytest.skip(f"{name} cannot be imported ({e}); install every extra (scripts/test.sh)")
        for item in getattr(module, "__all__", ()):
            obj = getattr(module, item)
            paths = {f"{name}.{item}", *_defined_at(obj, item)}
            names[f"{name}.{item}"] = paths
            if inspect.isclass(obj) and obj.__module__.startswith("rlu"):
                for attr, value in vars(obj).items():
                    if attr.startswith("_") or not _is_method(value):
                        continue
                    names[f"{name}.{item}.{attr}"] = {f"{p}.{attr}" for p in paths}
    return names


def _is_method(value: object) -> bool:
    return inspect.isfunction(value) or isinstance(value, (property, staticmethod, classmethod))


def _defined_at(obj: object, item: str) -> set[str]:
    """Where an object is defined: a class's or function's own module and name; for a value (a
    constant), every rlu module that assigns ``item`` at its top level to that very object."""
    if inspect.isclass(obj) or inspect.isfunction(obj):
        return {f"{obj.__module__}.{obj.__qualname__}"}
    out = set()
    for name, module in list(sys.modules.items()):
        if not name.startswith("rlu") or getattr(module, item, _NONE) is not obj:
            continue
        if item in _assigned(getattr(module, "__file__", None)):
            out.add(f"{name}.{item}")
    return out


_NONE = object()
_ASSIGNED: dict[str, set[str]] = {}


def _assigned(path: str | None) -> set[str]:
    if path is None:
        return set()
    if path not in _ASSIGNED:
        tree = ast.parse(Path(path).read_text())
        found = set()
        for node in tree.body:
            targets = node.targets if isinstance(node, ast.Assign) else []
            if isinstance(node, ast.AnnAssign):
                targets = [node.target]
            found |= {t.id for t in targets if isinstance(t, ast.Name)}
        _ASSIGNED[path] = found
    return _ASSIGNED[path]


def _inventory(site: Path) -> set[str]:
    """The objects of a site's ``objects.inv`` (Sphinx's format: four header lines, then zlib)."""
    raw = (site / "objects.inv").read_bytes().split(b"\n", 4)
    body = zlib.decompress(raw[4]).decode()
    return {line.split(" ", 1)[0] for line in body.splitlines() if line.strip()}


def _sources() -> list[Path]:
    return [
        ROOT / "mkdocs.yml",
        *(ROOT / "docs").rglob("*"),
        *(ROOT / "rlu").rglob("*.py"),
        *(ROOT / "scripts").glob("docs_*.py"),
    ]


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    built = ROOT / "build" / "site"
    inv = built / "objects.inv"
    if inv.is_file() and inv.stat().st_mtime >= max(p.stat().st_mtime for p in _sources()):
        return built  # what the test command built a moment ago
    mkdocs = Path(sys.executable).with_name("mkdocs")
    if not mkdocs.exists():
        pytest.skip("mkdocs is not installed (the docs extra: bash scripts/install.sh docs)")
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1", "PYTHONPATH": str(ROOT)}
    res = subprocess.run([str(mkdocs), "build", "--quiet", "--site-dir", str(out)], cwd=ROOT,
                         env=env, capture_output=True, text=True)  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    return out


def test_every_public_name_has_a_docstring():
    missing = []
    for name in public_names():
        module_name, _, attr = name.rpartition(".")
        parent: object
        try:
            parent = importlib.import_module(module_name)
        except ImportError:
            owner, _, cls = module_name.rpartition(".")
            parent = getattr(importlib.import_module(owner), cls)
        # a class's own attribute as defined (a property, not its value); a module's lazily
        obj = (
            inspect.getattr_static(parent, attr)
            if inspect.isclass(parent)
            else getattr(parent, attr)
        )
        obj = obj.fget if isinstance(obj, property) else getattr(obj, "__func__", obj)
        if (inspect.isclass(obj) or inspect.isfunction(obj)) and not obj.__doc__:
            missing.append(name)
        # a dataclass without one gets ``Name(field: type, ...)`` from dataclasses: not a doc
        if inspect.isclass(obj) and (obj.__doc__ or "").startswith(f"{obj.__name__}("):
            missing.append(name)
    assert missing == [], f"{len(missing)} public names without a docstring: {missing}"


def test_every_public_name_is_on_the_site(site):
    documented = _inventory(site)
    names = public_names()
    missing = sorted(name for name, paths in names.items() if not paths & documented)
    assert missing == [], f"{len(missing)} of {len(names)} public names not on the site: {missing}"
    assert len(names) > 250  # the walk found the API (a broken walk would pass on nothing)


def test_the_home_page_shows_the_one_line_load_and_it_runs(monkeypatch, tmp_path):
    import re

    home = (ROOT / "docs" / "index.md").read_text()
    assert 'ds = rlu.load_dataset("control_suite/cartpole_swingup")' in home
    pytest.importorskip("dm_control")
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    for block in re.findall(r"^```python\n(.*?)^```", home, flags=re.S | re.M):
        exec(compile(block, "docs/index.md", "exec"), scope)  # noqa: S102 - the page's own code
    assert len(scope["ds"]) == 40 and scope["batch"].action.shape == (256, 1)
