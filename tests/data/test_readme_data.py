"""The README's first data snippet runs as written (on the dataset rlu ships)."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[2] / "README.md"


def test_readme_first_data_snippet_runs():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    snippet = next(b for b in blocks if "transition_sampler(" in b)
    assert 'rlu.load_dataset("control_suite/cartpole_swingup")' in snippet
    scope: dict = {}
    exec(compile(snippet, str(README), "exec"), scope)  # noqa: S102 - the README's own code
    assert scope["batch"].observation["position"].shape == (256, 3)
    assert scope["seqs"].mask.shape[:2] == (16, 40)
