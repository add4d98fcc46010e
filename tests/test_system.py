"""rlu.system: install hints that fit how rlu was installed."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from rlu.system import install_hint

ROOT = Path(__file__).resolve().parents[1]


def test_install_hint_names_the_pip_extras_and_the_script_in_a_checkout():
    hint = install_hint("control", "agents")
    assert hint.startswith('pip install "rlu[control,agents]"')
    assert "bash scripts/install.sh control agents" in hint  # this test runs from a checkout


def test_install_hint_without_a_checkout_names_pip_only(tmp_path):
    """rlu as a wheel installs it: the package alone, no scripts/ beside it."""
    shutil.copytree(ROOT / "rlu", tmp_path / "rlu", ignore=shutil.ignore_patterns("resources"))
    code = (
        "import rlu.system; from rlu.system import install_hint; "
        "print(rlu.system.__file__); print(install_hint('control', 'agents'))"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env,
        check=True,
    )  # fmt: skip
    where, hint = out.stdout.strip().splitlines()
    assert Path(where).is_relative_to(tmp_path)
    assert hint == 'pip install "rlu[control,agents]"'
