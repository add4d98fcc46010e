"""Facts about the machine and the installation that every part of rlu may ask for: the CPU
cores this process may use and how to install a missing extra. Standard library only."""

from __future__ import annotations

import os


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask, which containers and taskset
    narrow; ``os.cpu_count()`` counts the whole machine)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def install_hint(*extras: str) -> str:
    """How to install the pip extras ``extras`` of rlu, as the user installed rlu: the pip line
    always, and ``bash scripts/install.sh`` too when rlu runs from a checkout (the script is not
    in the wheel)."""
    hint = f'pip install "rlu[{",".join(extras)}]"'
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if os.path.exists(os.path.join(root, "scripts", "install.sh")):
        hint += f" (in this checkout: bash scripts/install.sh {' '.join(extras)})"
    return hint
