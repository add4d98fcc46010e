"""The registry of foreign dataset formats rlu imports and exports (D4RL, d3rlpy, Minari).

A format is one module plus one line here, as Minari's ``_storages`` registry names its storage
backends: the module (one of rlu's own, imported when the format is used) defines

    export(ds, out, *, overwrite, note, **options) -> Path
    import_dataset(src, dest, task_id, **options) -> Path

and this line gives its name, the extra that installs what it imports, the help of its target
and source, and the options it takes beyond them. ``rlu export`` / ``rlu import`` take their
``--format`` choices, help, dispatch and extras from here, and so does the missing-extra
message of every command (``rlu.cli``).

Standard library only.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType, ModuleType
from typing import Any

from rlu.types import RluError


@dataclass(frozen=True)
class Option:
    """A format's own option (``--id``): its flag, its help, and which commands take it."""

    flag: str
    help: str
    commands: tuple[str, ...] = ("export", "import")
    """'export', 'import' or both."""

    @property
    def dest(self) -> str:
        return self.flag.lstrip("-").replace("-", "_")


@dataclass(frozen=True)
class Format:
    """One foreign format (see the module docstring)."""

    name: str
    module: str
    """rlu's module that reads and writes it (``export`` / ``import_dataset``)."""
    extra: str
    """The pyproject extra that installs its libraries."""
    packages: tuple[str, ...]
    """Python packages the module imports (a missing one names ``extra``)."""
    target: str | None
    """Help of ``rlu export -o`` for this format; None: the format takes no ``-o`` (its options
    name the target)."""
    source: str
    """Help of ``rlu import SRC`` for this format."""
    task_required: bool
    """``rlu import`` needs ``--task`` (unless the file is an export of rlu's)."""
    options: tuple[Option, ...] = ()


FORMATS: Mapping[str, Format] = MappingProxyType(
    {
        f.name: f
        for f in (
            Format(
                "d4rl",
                "rlu.data.d4rl",
                "interop",
                ("h5py",),
                "X.hdf5 (D4RL's HDF5 layout) or X.npz (numpy)",
                ".npz or .hdf5 file",
                True,
            ),
            Format(
                "d3rlpy",
                "rlu.data.d3rlpy_io",
                "interop",
                ("h5py",),
                "X.h5, the file d3rlpy's ReplayBuffer.dump writes (ReplayBuffer.load reads it)",
                "the .h5 of MDPDataset.dump",
                True,
            ),
            Format(
                "minari",
                "rlu.data.minari",
                "interop",
                ("minari", "h5py"),
                None,
                "a dataset id or directory",
                False,
                (
                    Option(
                        "--id",
                        "Minari dataset id NAMESPACE/NAME-vN (default for a dataset imported "
                        "from Minari: its own id)",
                        ("export",),
                    ),
                    Option(
                        "--minari-dir",
                        "Minari datasets directory (default: $MINARI_DATASETS_PATH or "
                        "~/.minari/datasets)",
                    ),
                ),
            ),
        )
    }
)


def get_format(name: str) -> Format:
    """The registered format ``name``; an unknown one is an RluError listing them."""
    if name not in FORMATS:
        raise RluError(f"unknown format {name!r}; formats: {', '.join(FORMATS)}")
    return FORMATS[name]


def format_module(name: str) -> ModuleType:
    """The module of format ``name`` (rlu's own, named by the registry: never by a file)."""
    return importlib.import_module(get_format(name).module)


def options_of(name: str, command: str, given: Mapping[str, Any]) -> dict[str, Any]:
    """The options of format ``name`` that ``command`` takes, from ``given`` (argparse's dests);
    an option given for a format that does not take it is an RluError."""
    fmt = get_format(name)
    mine = {o.dest for o in fmt.options if command in o.commands}
    every = {o.dest for f in FORMATS.values() for o in f.options}
    stray = sorted(k for k in every - mine if given.get(k) is not None)
    if stray:
        flags = ", ".join("--" + k.replace("_", "-") for k in stray)
        raise RluError(f"{flags} does not apply to rlu {command} --format {name}")
    return {k: given.get(k) for k in mine}


def export_dataset(
    name: str,
    ds: Any,
    out: str | os.PathLike | None,
    overwrite: bool = False,
    note: Any = None,
    **options: Any,
) -> Path:
    """Export dataset ``ds`` in format ``name`` to ``out`` (or where its options say)."""
    fmt = get_format(name)
    if fmt.target is not None and out is None:
        raise RluError(f"--format {name} needs -o/--out: {fmt.target}")
    if fmt.target is None and out is not None:
        flags = " and ".join(o.flag for o in fmt.options if "export" in o.commands)
        raise RluError(f"--format {name} takes no -o; give {flags}")
    return format_module(name).export(ds, out, overwrite=overwrite, note=note, **options)


def import_dataset(
    name: str, src: str | os.PathLike, dest: str | os.PathLike, task_id: str | None, **options: Any
) -> Path:
    """Import ``src`` of format ``name`` into a new rlu dataset at ``dest``."""
    return format_module(name).import_dataset(src, dest, task_id, **options)


def extras_of_packages() -> dict[str, str]:
    """{package: extra} for every package a format imports (``rlu.cli``'s missing-extra line)."""
    return {p: f.extra for f in FORMATS.values() for p in f.packages}
