"""A new domain is one module plus one registry line: a copy of the package gains
``rlu/domains/corridor.py`` (its task, its env, its entry) and ``"corridor"`` in ``_MODULES``,
nothing else, and the command line lists it, trains an agent on its data, evaluates the run in
its env and reports it. Real processes on the copy (``python -m rlu``), no edit of the repo."""

from __future__ import annotations

import difflib
import filecmp
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

CORRIDOR = '''"""corridor: a toy domain of one task, an 8-cell corridor walked left or right."""

from __future__ import annotations

from types import MappingProxyType
from typing import Any

import numpy as np

from rlu.domains import Domain
from rlu.domains.common import f32


def build_tasks() -> list:
    from rlu.domains.spec import TaskSpec
    from rlu.types import DiscreteSpec

    return [
        TaskSpec(
            id="corridor/walk",
            domain="corridor",
            name="walk",
            observation_spec=f32(4),
            action_spec=DiscreteSpec((), "int64", 2),
            episode_length=16,
            selection="offline",
            episodes=MappingProxyType({}),
            release=(),
        )
    ]


def make(task: Any, seed: int | None = None, render: Any = None, **settings: Any) -> Any:
    from rlu.envs.core import gym, observation_space, spaces

    class Walk(gym.Env):
        metadata = {"render_modes": []}

        def __init__(self) -> None:
            self.observation_space = observation_space(task.observation_spec)
            self.action_space = spaces.Discrete(2)
            self.cell = self.t = 0

        def _obs(self) -> np.ndarray:
            return np.array([self.cell / 7, 1.0, 0.0, 0.0], np.float32)

        def reset(self, *, seed: int | None = None, options: dict | None = None):
            super().reset(seed=seed)
            self.cell = self.t = 0
            return self._obs(), {}

        def step(self, action: Any):
            self.cell = min(7, max(0, self.cell + (1 if int(action) == 1 else -1)))
            self.t += 1
            done = self.cell == 7  # an env ends its episodes: truncated at the task's length
            return self._obs(), float(done), done, self.t >= task.episode_length, {}

    return Walk()


DOMAIN = Domain(
    name="corridor",
    title="Corridor",
    build_tasks=build_tasks,
    env_module="rlu.domains.corridor",
    extra="control",
    packages=("gymnasium",),
)
'''

SYNTHETIC = """
import sys
from rlu.data import Schema
from rlu.data.synthetic import write_synthetic
from rlu.tasks import get_task
write_synthetic(sys.argv[1], Schema.for_task(get_task("corridor/walk")), 6, 16, seed=0)
"""


def _changes(a: Path, b: Path) -> tuple[list[str], list[str]]:
    """Files only in ``b`` and changed lines (unified diff) between the two package trees."""
    added, changed = [], []
    for left, right in [(a, b)]:
        stack = [filecmp.dircmp(left, right, ignore=["__pycache__"])]
        while stack:
            d = stack.pop()
            added += [str(Path(d.right, n).relative_to(b)) for n in d.right_only]
            for name in d.diff_files:
                x = Path(d.left, name).read_text().splitlines()
                y = Path(d.right, name).read_text().splitlines()
                changed += [
                    f"{Path(d.right, name).relative_to(b)}: {line}"
                    for line in difflib.unified_diff(x, y, lineterm="", n=0)
                    if line[:1] in "+-" and not line.startswith(("+++", "---"))
                ]
            stack.extend(d.subdirs.values())
    return added, changed


@pytest.mark.slow  # several processes importing torch: ~30 s on a 2-core machine
def test_a_domain_added_as_one_module_and_one_line_lists_trains_evaluates_and_reports(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("gymnasium")
    copy = tmp_path / "copy"
    shutil.copytree(ROOT / "rlu", copy / "rlu", ignore=shutil.ignore_patterns("__pycache__"))
    (copy / "rlu" / "domains" / "corridor.py").write_text(CORRIDOR)
    registry = copy / "rlu" / "domains" / "__init__.py"
    text = registry.read_text()
    line = next(x for x in text.splitlines() if x.startswith("_MODULES = ("))
    registry.write_text(text.replace(line, line.replace(")", ', "corridor")'), 1))

    added, changed = _changes(ROOT / "rlu", copy / "rlu")
    assert added == ["domains/corridor.py"]
    assert len(changed) == 2 and all(c.startswith("domains/__init__.py: ") for c in changed)

    env = {**os.environ, "PYTHONPATH": str(copy), "RLU_DECODERS": "0"}

    def rlu(*args: str) -> subprocess.CompletedProcess:
        done = subprocess.run([sys.executable, "-m", "rlu", *args], cwd=copy, env=env,
                              capture_output=True, text=True, timeout=600)  # fmt: skip
        assert "Traceback" not in done.stderr, done.stderr
        return done

    listed = rlu("list")
    assert listed.returncode == 0 and "corridor/walk" in listed.stdout, listed.stdout
    data, run = tmp_path / "data", tmp_path / "run"
    made = subprocess.run([sys.executable, "-c", SYNTHETIC, str(data)], cwd=copy, env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert made.returncode == 0, made.stderr
    trained = rlu("train", "--task", "corridor/walk", "--agent", "dqn", "--dataset", str(data),
                  "--out", str(run), "--steps", "3", "--eval-every", "0", "--eval-episodes", "1",
                  "--eval-envs", "1", "--device", "cpu", "--quiet",
                  "atari.batch_size=4")  # fmt: skip
    assert trained.returncode == 0, trained.stderr
    result = json.loads((run / "result.json").read_text())
    assert result["steps"] == 3 and 1 <= result["final_eval"]["lengths"][0] <= 16
    evaluated = rlu("evaluate", str(run), "--eval-episodes", "2", "--json")
    assert evaluated.returncode == 0, evaluated.stderr
    assert len(json.loads(evaluated.stdout)["returns"]) == 2
    reported = rlu("report", str(run), "--out", str(tmp_path / "report"))
    assert reported.returncode == 0, reported.stderr
    assert (tmp_path / "report" / "report.md").exists()
