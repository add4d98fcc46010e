"""A new domain is one module plus one registry line: a copy of the package gains
``rlu/domains/corridor.py`` (its task, its env, its release family, its entry) and ``"corridor"``
in ``_MODULES``, nothing else, and the command line lists it, converts a shard of its release
format, trains an agent on the data, evaluates the run in its env and reports it. Real processes
on the copy (``python -m rlu``), no edit of the repo."""

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
from rlu.domains.records import Family, integers, need, numeric


def build_tasks() -> list:
    from rlu.domains.spec import ReleaseDataset, TaskSpec
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
            release=(ReleaseDataset("corridor", "corridor/walk", MappingProxyType({"": 1})),),
        )
    ]


def parse(cols: Any, where: str = "record") -> list:
    """Whole episodes: T 4-float observations, T int64 actions, T rewards."""
    action = integers(numeric(need(cols, "action", where), "action", where), "action", where)
    t = action.shape[1]
    obs = numeric(need(cols, "observation", where), "observation", where)
    reward = numeric(need(cols, "reward", where), "reward", where)
    return [{"observation": obs.reshape(-1, t, 4), "action": action, "reward": reward}]


def segments(raw: Any) -> Any:
    from rlu.segments import SegmentBatch

    n, t = raw["action"].shape
    first, last = np.zeros((n, t), bool), np.zeros((n, t), bool)
    first[:, 0] = last[:, -1] = True
    discount = np.ones((n, t), np.float32)
    discount[:, -2:] = 0.0  # every episode ends at the corridor's end: terminal
    return SegmentBatch(raw["observation"].astype(np.float32), raw["action"],
                        raw["reward"].astype(np.float32), discount, first, last, last.copy())


def encode(rec: Any) -> bytes:
    from rlu.codecs import example as ex

    feats = {k: np.asarray(v).reshape(-1) for k, v in rec.items()}
    kinds = {"observation": ex.FLOAT, "action": ex.INT64, "reward": ex.FLOAT}
    return ex.encode_example(feats, kinds=kinds)


FAMILIES = (
    Family(name="corridor", compression=None, parse=parse, segments=segments, encode=encode,
           whole_episodes=True, max_record_bytes=1 << 20, max_shard_bytes=1 << 24,
           record_note="a corridor episode is 16 steps of 6 floats"),
)


def make(task: Any, seed: int | None = None, render: Any = None, **settings: Any) -> Any:
    from rlu.domains.envkit import gym, observation_space, spaces

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
    release_module="rlu.domains.corridor",
    extra="control",
    packages=("gymnasium",),
)
'''

# a release shard of the corridor's family, written by its own encoder: 6 episodes walking right
SHARD = """
import sys
import numpy as np
from rlu.data.release.families import write_shard
rng = np.random.default_rng(0)
records = []
for _ in range(6):
    actions = np.concatenate([rng.integers(0, 2, 6), np.ones(7, np.int64)])
    cells = np.minimum(7, np.maximum(0, np.cumsum(np.concatenate([[0], 2 * actions - 1]))))
    t = int(np.argmax(cells == 7)) + 1 if (cells == 7).any() else len(cells)
    obs = np.stack([cells[:t] / 7, np.ones(t), np.zeros(t), np.zeros(t)], 1).astype(np.float32)
    reward = np.zeros(t, np.float32)
    reward[-2] = 1.0
    records.append({"observation": obs, "action": np.append(actions, 0)[:t], "reward": reward})
write_shard(sys.argv[1], "corridor", records)
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
def test_a_domain_added_as_one_module_and_one_line_lists_converts_trains_evaluates_reports(
    tmp_path,
):
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
    shard = tmp_path / "corridor" / "walk-00000-of-00001"
    shard.parent.mkdir()
    made = subprocess.run([sys.executable, "-c", SHARD, str(shard)], cwd=copy, env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert made.returncode == 0, made.stderr
    converted = rlu("convert", str(shard), "--family", "corridor", "--task", "corridor/walk",
                    "--out", str(data))  # fmt: skip
    assert converted.returncode == 0, converted.stderr
    assert ": 6 segments, 74 steps from 6 records" in converted.stdout, converted.stdout
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
