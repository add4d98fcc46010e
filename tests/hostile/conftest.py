"""Fixtures for hostile-input tests: a record of every file Python opens (``sys.audit``'s "open"
event: ``open``, ``os.open``, ``np.memmap``, ``np.fromfile`` all raise it), so a test can prove
that nothing outside a dataset's folder was read."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

_OPENED: list[str] | None = None


def _hook(event: str, args: tuple) -> None:
    if _OPENED is not None and event == "open" and args and isinstance(args[0], (str, bytes)):
        path = args[0].decode() if isinstance(args[0], bytes) else args[0]
        _OPENED.append(os.path.realpath(path))


sys.addaudithook(_hook)  # hooks cannot be removed: this one records only while a test asks


class Opened:
    """Paths opened while the fixture is active (resolved: symlinks followed)."""

    def __init__(self, log: list[str]):
        self.log = log

    def under(self, root: Path) -> list[str]:
        base = os.path.realpath(root)
        return [p for p in self.log if p == base or p.startswith(base + os.sep)]


@pytest.fixture
def opened():
    global _OPENED
    _OPENED = []
    try:
        yield Opened(_OPENED)
    finally:
        _OPENED = None
