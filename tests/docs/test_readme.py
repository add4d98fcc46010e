"""The README is the front door: its links lead into docs/ (which mkdocs does not check, the
README being outside the site) and its Python runs as written."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _anchors(page: Path) -> set[str]:
    from markdown.extensions.toc import slugify

    text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.S | re.M)
    return {slugify(h.strip("` "), "-") for h in re.findall(r"^#{1,6} (.+)$", text, flags=re.M)}


def test_readme_links_lead_to_files_and_headings():
    pytest.importorskip("markdown")  # the site's anchors are Python-Markdown's
    links = [t for t in LINK.findall(README.read_text()) if "://" not in t]
    assert any(t.startswith("docs/") for t in links), "the README links into docs/"
    for target in links:
        path, _, anchor = target.partition("#")
        file = ROOT / path
        assert file.is_file(), f"README.md links to {target}: no such file"
        if anchor:
            assert anchor in _anchors(file), f"README.md links to {target}: no such heading"


def test_readme_python_runs(tmp_path, monkeypatch):
    pytest.importorskip("dm_control")
    blocks = re.findall(r"^```python\n(.*?)^```", README.read_text(), flags=re.S | re.M)
    assert blocks
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))
    scope: dict = {}
    for block in blocks:
        exec(compile(block, str(README), "exec"), scope)  # noqa: S102 - the README's own code
    assert scope["batch"].observation["position"].shape == (256, 3)
    assert scope["seqs"].mask.shape[:2] == (16, 40)


@pytest.mark.slow
def test_the_readme_set_up_commands_run_as_written():
    """The README's first command, as written, in the checkout CI cloned fresh (the second is
    the command that runs this test): it installs what the quick start needs and runs the quick
    start, whose finding must hold (the best offline RL agent at 1.5 times BC or more, and 600
    or more)."""
    import json
    import shutil
    import subprocess

    pytest.importorskip("dm_control")
    text = README.read_text()
    block = re.search(r"^```bash\n(.*?)^```", text, flags=re.S | re.M).group(1)
    commands = [line for line in block.splitlines() if line and not line.startswith("#")]
    assert commands[1] == "bash scripts/test.sh"  # this test runs inside it
    out = ROOT / "runs" / "quickstart"
    shutil.rmtree(out, ignore_errors=True)
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    res = subprocess.run(["bash", "-c", commands[0]], cwd=ROOT, env=env, capture_output=True,
                         text=True)  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    result = json.loads((out / "results.json").read_text())
    means = {p["policy"]: p["mean"] for p in result["policies"]}
    best = max(v for k, v in means.items() if k not in ("random", "bc"))
    assert best >= 1.5 * means["bc"] and best >= 600, means
    assert (out / "quickstart.png").stat().st_size > 10_000  # the report extra draws it
