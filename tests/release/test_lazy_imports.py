"""Importing the release package costs numpy only: Pillow and google-crc32c load on first use."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def test_release_modules_import_lazily():
    code = (
        "import sys, rlu.data.release.framing, rlu.codecs.example, rlu.codecs.png, "
        "rlu.data.release.families, rlu.data.release.catalog, rlu.data.release.download, "
        "rlu.data.release.convert, rlu.data.release.load, rlu.commands.release;"
        "print(','.join(m for m in ('PIL', 'google_crc32c', 'tensorflow', 'google.protobuf') "
        "if m in sys.modules))"
    )
    root = Path(__file__).resolve().parents[2]
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""
