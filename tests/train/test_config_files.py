"""Run configs as files: rlu train --config (YAML or JSON, or a run folder's config.json), the
options typed beside it winning, and the names in it never imported."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TASK = "control_suite/cartpole_swingup"


def _rlu(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "rlu", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True)  # fmt: skip


@pytest.fixture
def yaml_config(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("yaml")
    from rlu.data.bundled import bundled_dataset

    path = tmp_path / "bc.yaml"
    path.write_text(
        f"task: {TASK}\nagent: bc\ndataset: {bundled_dataset()}\nseed: 3\n"
        "overrides:\n  batch_size: 8\n  learning_rate: 0.002\n"
        "run:\n  steps: 6\n  eval_every: -1\n  checkpoint_every: 3\n  log_every: 2\n"
    )
    return path


def test_a_yaml_config_runs_and_typed_options_win(yaml_config, tmp_path):
    res = _rlu("train", "--config", str(yaml_config), "--out", str(tmp_path / "a"),
               "--steps", "4", "--no-progress")  # fmt: skip
    assert res.returncode == 0, res.stderr
    config = json.loads((tmp_path / "a" / "config.json").read_text())
    assert config["train"]["seed"] == 3 and config["train"]["run"]["steps"] == 4
    assert config["train"]["run"]["log_every"] == 2
    assert config["agent_config"]["batch_size"] == 8
    assert config["agent_config"]["learning_rate"] == 0.002
    # a typed override beats the file's
    res = _rlu("train", "--config", str(yaml_config), "--out", str(tmp_path / "b"),
               "--no-progress", "learning_rate=0.005")  # fmt: skip
    assert res.returncode == 0, res.stderr
    config = json.loads((tmp_path / "b" / "config.json").read_text())
    assert config["agent_config"]["learning_rate"] == 0.005 and config["train"]["run"]["steps"] == 6


def test_a_run_folders_config_runs_again_to_the_same_numbers(yaml_config, tmp_path):
    first = tmp_path / "first"
    assert _rlu("train", "--config", str(yaml_config), "--out", str(first),
                "--no-progress").returncode == 0  # fmt: skip
    again = tmp_path / "again"
    res = _rlu("train", "--config", str(first / "config.json"), "--out", str(again),
               "--no-progress")  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert (again / "metrics.jsonl").read_text() == (first / "metrics.jsonl").read_text()


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("agent: tests.train.fake_agent\n", "field 'agent' names an agent module"),
        ("run:\n  env: os:system\n", "field 'env' names an env factory"),
        ("a: &x [1, 2]\nb: [*x, *x]\n", "YAML aliases"),
        ("task: [unclosed\n", "not valid YAML"),
        ("run:\n  stepz: 3\n", "field 'run.stepz' is not a known field"),
        ("run:\n  steps: many\n", "field 'run.steps' is a string"),
    ],
    ids=["agent_module", "env_factory", "alias", "broken", "unknown", "wrong_type"],
)
def test_bad_config_files_are_one_line(yaml_config, tmp_path, text, says):
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml_config.read_text() + "\n" + text if "run:" not in text else
                   yaml_config.read_text().split("run:")[0] + text)  # fmt: skip
    res = _rlu("train", "--config", str(bad), "--out", str(tmp_path / "o"), "--no-progress")
    assert res.returncode == 2, res.stderr
    lines = [x for x in res.stderr.strip().splitlines() if not x.startswith("rlu train: ")]
    assert len(lines) == 1 and says in lines[0] and "Traceback" not in res.stderr, res.stderr
    assert not (tmp_path / "o").exists()


def test_a_module_typed_beside_the_file_is_trusted(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("yaml")
    from tests.train.pendulum import write_dataset

    data = write_dataset(tmp_path / "data", "test/pendulum", episodes=4)
    path = tmp_path / "fake.json"
    env = "tests.train.pendulum:make_env"
    path.write_text(json.dumps({"task": "test/pendulum", "agent": "tests.train.fake_agent",
                                "dataset": str(data), "run": {"steps": 2, "eval_every": -1,
                                                              "env": env}}))  # fmt: skip
    res = _rlu("train", "--config", str(path), "--out", str(tmp_path / "o"), "--no-progress",
               "--agent", "tests.train.fake_agent", "--env", env)  # fmt: skip
    assert res.returncode == 0, res.stderr
