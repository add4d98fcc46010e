"""rlu: RL Unplugged without TensorFlow.

The public API is imported lazily so that ``import rlu`` needs numpy only:
``load_dataset``, ``make_env``, ``make_agent``, ``evaluate``, ``list_tasks``, ``get_task``,
``report`` (tables and figures of run and sweep folders).
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"
"""rlu's version (``rlu --version`` prints it)."""

_LAZY = {
    "list_tasks": "rlu.tasks",
    "get_task": "rlu.tasks",
    "TaskSpec": "rlu.tasks",
    "load_dataset": "rlu.data",
    "open_dataset": "rlu.data",
    "make_env": "rlu.envs",
    "make_agent": "rlu.agents",
    "evaluate": "rlu.evaluation",
    "report": "rlu.report",
}

__all__ = sorted(_LAZY) + ["__version__"]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'rlu' has no attribute {name!r}")
