"""The datasets shipped inside the package (``rlu/resources/datasets/<task id>``).

rlu ships one: ``control_suite/cartpole_swingup``, the paper's 40 episodes made by ``rlu generate
control_suite/cartpole_swingup --scale laptop --seeds 3 --seed 0`` (its manifest's provenance
holds the command and seed).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from rlu.types import RluError

MANIFEST = "manifest.json"


def _root() -> Path:
    return Path(str(resources.files("rlu"))) / "resources" / "datasets"


def bundled_dataset_path(task_id: str) -> Path | None:
    """The folder of the dataset shipped for ``task_id`` (a registry id), or None."""
    path = _root().joinpath(*task_id.split("/"))
    return path if (path / MANIFEST).is_file() else None


def bundled_tasks() -> list[str]:
    """The task ids rlu ships a dataset for."""
    root = _root()
    return sorted(p.parent.relative_to(root).as_posix() for p in root.glob(f"*/*/{MANIFEST}"))


def bundled_dataset(task_id: str | None = None) -> Path:
    """The folder of the dataset shipped for ``task_id``; None: the one dataset rlu ships (made
    by ``rlu generate``; its manifest holds the command and seed)."""
    shipped = bundled_tasks()
    if task_id is None and len(shipped) == 1:
        task_id = shipped[0]
    path = bundled_dataset_path(task_id) if task_id is not None else None
    if path is None:
        raise RluError(
            f"{_root()}: no bundled dataset for {task_id!r}; the package ships "
            f"{', '.join(shipped) or 'none'} (reinstall rlu if one is missing)"
        )
    return path
