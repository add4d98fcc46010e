"""The tutorials' code runs as written: each page's ``python`` blocks, in order, as one script in
an empty folder (what a reader who pastes them one after the other gets)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TUTORIALS = sorted(p for p in (ROOT / "docs" / "tutorials").glob("*.md") if p.name != "index.md")
BLOCK = re.compile(r"^```python\n(.*?)^```\s*$", re.S | re.M)


def tutorial_code(page: Path) -> str:
    blocks = BLOCK.findall(page.read_text())
    assert blocks, f"{page}: a tutorial without a python block"
    return "\n\n".join(blocks)


def test_every_tutorial_is_found():
    assert {p.stem for p in TUTORIALS} >= {"data", "envs", "train_export"}


def test_blocks_are_extracted_in_order(tmp_path):
    page = tmp_path / "t.md"
    page.write_text("text\n\n```python\na = 1\n```\n\n```bash\nno\n```\n\n```python\nb = a\n```\n")
    assert tutorial_code(page) == "a = 1\n\n\nb = a\n"


@pytest.mark.parametrize("page", TUTORIALS, ids=lambda p: p.stem)
def test_tutorial_runs(page, tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    script = tmp_path / f"{page.stem}.py"
    script.write_text(tutorial_code(page))
    work = tmp_path / "work"
    work.mkdir()
    env = dict(os.environ, PYTHONPATH=str(ROOT), MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    proc = subprocess.run(
        [sys.executable, str(script)], cwd=work, env=env, capture_output=True, text=True,
        timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, f"{page.name} failed:\n{proc.stdout}\n{proc.stderr}"
    assert proc.stdout.strip(), f"{page.name} printed nothing"
