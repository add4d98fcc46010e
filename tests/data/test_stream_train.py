"""`rlu train` on a mixture of datasets (streamed): the command line (repeated --dataset, a glob,
--weights, --sampler), the resolved config, and an exact resume from a checkpoint."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from rlu.types import RluError

ROOT = Path(__file__).resolve().parents[2]
ENV = "tests.train.pendulum:make_env"
AGENT = "tests.train.fake_agent"


@pytest.fixture(scope="module")
def pendulums(tmp_path_factory):
    pytest.importorskip("gymnasium")
    pytest.importorskip("torch")
    from tests.train.pendulum import write_dataset

    root = tmp_path_factory.mktemp("mixture")
    return [str(write_dataset(root / f"pendulum_{i}", "test/pendulum", seed=i)) for i in range(3)]


def _cli(args: list[str], env_extra: dict | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, **(env_extra or {})}
    return subprocess.run([sys.executable, "-m", "rlu", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True)  # fmt: skip


def _args(datasets: list[str], out: Path) -> list[str]:
    return [
        "train", "--task", "test/pendulum", "--agent", AGENT, *datasets, "--env", ENV,
        "--steps", "60", "--eval-every", "-1", "--log-every", "10", "--checkpoint-every", "25",
        "--threads", "1", "--no-progress", "--stream-memory", "16", "--out", str(out),
    ]  # fmt: skip


def test_mixture_from_the_command_line(pendulums, tmp_path):
    glob = str(Path(pendulums[0]).parent / "pendulum_[12]")
    given = ["--dataset", pendulums[0], "--dataset", glob, "--weights", "2", "1", "1"]
    done = _cli(_args(given, tmp_path / "run"))
    assert done.returncode == 0, done.stderr
    resolved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert resolved["train"]["dataset"] == pendulums
    assert resolved["train"]["weights"] == [2.0, 1.0, 1.0]
    assert resolved["train"]["run"]["sampler"] == "auto"
    assert resolved["dataset"]["mixture"]["paths"] == [str(Path(p).resolve()) for p in pendulums]
    assert json.loads((tmp_path / "run" / "result.json").read_text())["steps"] == 60


def test_mixture_resumes_exactly(pendulums, tmp_path):
    """A run that stopped after its checkpoint at step 50 resumes there (the stream sampler's
    state restored) and ends as the uninterrupted run did."""
    from rlu.training.train import train
    from tests.fakes import train_config

    config = train_config(task="test/pendulum", agent=AGENT, dataset=tuple(pendulums), env=ENV,
                          weights=(2.0, 1.0, 1.0), steps=60, eval_every=-1, log_every=5,
                          checkpoint_every=25, torch_threads=1, stream_memory=16)  # fmt: skip
    train(config, tmp_path / "ref")
    run = tmp_path / "run"
    train(config, run)
    (run / "result.json").unlink()  # as if killed between the checkpoints at 50 and 60
    (run / "checkpoints" / "step_00000060.pt").unlink()
    assert (run / "checkpoints" / "step_00000050.pt").exists()
    train(config, run, resume=True)
    for name in ("metrics.jsonl", "result.json"):
        assert (run / name).read_text() == (tmp_path / "ref" / name).read_text(), name


def test_one_dataset_streamed_and_refusals(pendulums, tmp_path):
    from rlu.training.train import train
    from tests.fakes import train_config

    base = dict(task="test/pendulum", agent=AGENT, steps=5, eval_every=-1, env=ENV,
                torch_threads=1, stream_memory=16)  # fmt: skip
    train(train_config(dataset=pendulums[0], sampler="stream", **base), tmp_path / "one")
    assert json.loads((tmp_path / "one" / "result.json").read_text())["steps"] == 5
    with pytest.raises(RluError, match="--sampler stream"):
        train(train_config(dataset=tuple(pendulums), sampler="uniform", **base), tmp_path / "u")
    with pytest.raises(RluError, match="one positive number per dataset"):
        train_config(dataset=tuple(pendulums), weights=(1.0, 2.0), **base)
    with pytest.raises(RluError, match="weigh the datasets of a mixture"):
        train(train_config(dataset=pendulums[0], weights=(1.0,), **base), tmp_path / "w")
    bad = _cli(_args(["--dataset", str(tmp_path / "none_*")], tmp_path / "g"))
    assert bad.returncode != 0 and "matches no dataset folder" in bad.stderr
