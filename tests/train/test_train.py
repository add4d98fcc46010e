"""The training loop on a real env and a real PyTorch agent: run folder, exact resume after a
SIGKILL, evaluate, errors."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rlu.commands._options import parse_overrides
from rlu.seeds import derive_seed
from rlu.training.restore import evaluate_run
from rlu.training.train import TrainConfig, train
from rlu.types import RluError
from tests.fakes import train_config

ROOT = Path(__file__).resolve().parents[2]
ENV = "tests.train.pendulum:make_env"
AGENT = "tests.train.fake_agent"


def _config(dataset: str, **kw) -> TrainConfig:
    base = dict(
        task="test/pendulum",
        agent=AGENT,
        dataset=dataset,
        steps=120,
        eval_every=40,
        eval_episodes=3,
        eval_envs=2,
        log_every=10,
        checkpoint_every=25,
        env=ENV,
        torch_threads=1,
    )
    base.update(kw)
    return train_config(**base)


def _cli(args: list[str], env_extra: dict | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, **(env_extra or {})}
    return subprocess.run(
        [sys.executable, "-m", "rlu", *args], cwd=ROOT, env=env, capture_output=True, text=True
    )


def test_run_folder_contents(pendulum_datasets, tmp_path):
    cfg = _config(pendulum_datasets["test/pendulum"], overrides={"learning_rate": 0.02})
    result = train(cfg, tmp_path / "run")
    run = tmp_path / "run"
    resolved = json.loads((run / "config.json").read_text())
    assert resolved["agent_config"]["learning_rate"] == 0.02
    assert resolved["train"]["run"]["steps"] == 120
    metrics = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [m["step"] for m in metrics] == list(range(10, 121, 10))
    assert all(np.isfinite(m["actor/bc_loss"]) for m in metrics)
    evals = [json.loads(x) for x in (run / "eval.jsonl").read_text().splitlines()]
    assert [e["step"] for e in evals] == [40, 80, 120]
    assert all(len(e["returns"]) == 3 and e["lengths"] == [50, 50, 50] for e in evals)
    assert result["score"] == pytest.approx(np.mean(evals[-1]["returns"]))
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == [
        "step_00000100.pt",
        "step_00000120.pt",
    ]
    # a second train into the same folder without --resume is refused
    with pytest.raises(RluError, match="--resume"):
        train(cfg, run)
    # evaluate the checkpoint: same seeds, same returns as the loop's last evaluation
    res = evaluate_run(run, episodes=3, seed=derive_seed(0, 120), num_envs=3, env=ENV)
    assert list(res.returns) == evals[-1]["returns"]


def test_sigkill_at_random_step_then_resume_matches_uninterrupted(pendulum_datasets, tmp_path):
    dataset = pendulum_datasets["test/pendulum"]
    reference = tmp_path / "reference"
    train(_config(dataset), reference)

    kill_at = int(np.random.default_rng().integers(2, 119))
    args = [
        "train", "--task", "test/pendulum", "--agent", AGENT, "--dataset", dataset,
        "--env", ENV, "--steps", "120", "--eval-every", "40", "--eval-episodes", "3",
        "--eval-envs", "2", "--log-every", "10", "--checkpoint-every", "25", "--threads", "1",
        "--no-progress", "--out", str(tmp_path / "killed"),
    ]  # fmt: skip
    killed = _cli(args, {"RLU_TEST_SIGKILL_AT_UPDATE": str(kill_at)})
    assert killed.returncode == -signal.SIGKILL, (kill_at, killed.stderr)
    assert not (tmp_path / "killed" / "result.json").exists()
    resumed = _cli([*args, "--resume"])
    assert resumed.returncode == 0, resumed.stderr
    for name in ("metrics.jsonl", "eval.jsonl", "result.json"):
        assert (tmp_path / "killed" / name).read_text() == (reference / name).read_text(), (
            f"{name} differs after a SIGKILL at update {kill_at}"
        )
    import torch

    a = torch.load(reference / "checkpoints" / "step_00000120.pt", weights_only=True)
    b = torch.load(tmp_path / "killed" / "checkpoints" / "step_00000120.pt", weights_only=True)
    for k, v in a["agent"]["net"].items():
        assert torch.equal(v, b["agent"]["net"][k])


def test_resume_refuses_a_different_config(pendulum_datasets, tmp_path):
    dataset = pendulum_datasets["test/pendulum"]
    train(_config(dataset, steps=20, eval_every=-1), tmp_path / "r")
    with pytest.raises(RluError, match="different configuration"):
        train(_config(dataset, steps=30, eval_every=-1), tmp_path / "r", resume=True)


def test_bad_inputs_name_the_fix(pendulum_datasets, tmp_path):
    dataset = pendulum_datasets["test/pendulum"]
    with pytest.raises(RluError, match="no field"):
        train(_config(dataset, overrides={"no_such_field": 1}), tmp_path / "a")
    with pytest.raises(RluError, match="field=value"):
        parse_overrides(["learning_rate"])
    assert parse_overrides(["learning_rate=3e-4", "hidden=(8, 8)", "name=abc"]) == {
        "learning_rate": 3e-4,
        "hidden": (8, 8),
        "name": "abc",
    }
    with pytest.raises(RluError, match="module:function"):
        train(_config(dataset, env="nocolon"), tmp_path / "b")
    with pytest.raises(RluError, match="not an rlu run folder|no checkpoints"):
        evaluate_run(tmp_path)
    # a damaged config.json of an existing run: named, with the fix, never a traceback
    run = tmp_path / "c"
    train(_config(dataset, steps=2, eval_every=-1), run)
    (run / "config.json").write_text('{"train": ')
    with pytest.raises(RluError, match=r"config\.json: not valid JSON"):
        train(_config(dataset, steps=2, eval_every=-1), run, resume=True)
    with pytest.raises(RluError, match=r"config\.json: not valid JSON"):
        evaluate_run(run, env=ENV)


def test_cli_evaluate(pendulum_datasets, tmp_path):
    train(_config(pendulum_datasets["test/pendulum"], steps=10, eval_every=-1), tmp_path / "r")
    ckpt = tmp_path / "r" / "checkpoints" / "step_00000010.pt"
    out = _cli(["evaluate", str(ckpt), "--episodes", "2", "--envs", "2", "--json", "--env", ENV,
                "--agent", AGENT])  # fmt: skip
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert len(res["returns"]) == 2 and res["lengths"] == [50, 50]


def test_rwrl_easy_shard_trains_and_evaluates_in_its_challenge(tmp_path):
    """A converted combined-challenge-easy release shard: the loop evaluates in the easy env
    (its dummy observations exist only there), rlu evaluate does too, and a challenge whose
    observations differ is refused with a clear error."""
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    from rlu.data.release.convert import convert
    from rlu.tasks import get_task
    from rlu.types import RluError
    from tests.release.test_convert import _shard
    from tests.release.test_families import rwrl_record

    rng = np.random.default_rng(0)
    task = get_task("rwrl/cartpole_swingup")
    path = _shard(tmp_path, "rwrl", [rwrl_record(rng, 21, easy=True) for _ in range(3)],
                  "episodes.tfrecord-00000-of-00001")  # fmt: skip
    data = tmp_path / "easy"
    convert([path], "rwrl", task.id, data, challenge="easy", workers=1)
    config = train_config(task=task.id, agent="bc", dataset=str(data), steps=3, eval_every=0,
                         eval_episodes=1, eval_envs=1, eval_max_steps=5, torch_threads=1,
                         overrides={"hidden_size": 16, "batch_size": 8})  # fmt: skip
    result = train(config, tmp_path / "run")
    assert result["env_settings"] == {"challenge": "easy"}
    assert result["final_eval"]["lengths"] == [5]
    res = evaluate_run(tmp_path / "run", episodes=1, num_envs=1, max_steps=4)
    assert res.lengths == (4,)
    with pytest.raises(RluError, match="recorded under RWRL challenge 'easy'"):
        evaluate_run(tmp_path / "run", episodes=1, num_envs=1, challenge="none")
    with pytest.raises(RluError, match="drop --challenge"):
        train(dataclasses.replace(config, run=dataclasses.replace(config.run, challenge="none")),
              tmp_path / "run_none")  # fmt: skip


def test_eval_at_start_adds_step_0_and_changes_nothing_else(pendulum_datasets, tmp_path):
    """The option added to prove the run-settings value: one field in RunSettings and its use in
    the loop; its flag and help come from the field."""
    from rlu.cli import build_parser
    from rlu.commands._options import from_args
    from rlu.training.config import RunSettings

    data = pendulum_datasets["test/pendulum"]
    train(_config(data), tmp_path / "plain")
    train(_config(data, eval_at_start=True), tmp_path / "start")
    plain = (tmp_path / "plain" / "eval.jsonl").read_text().splitlines()
    start = (tmp_path / "start" / "eval.jsonl").read_text().splitlines()
    assert json.loads(start[0])["step"] == 0 and start[1:] == plain
    for name in ("metrics.jsonl", "result.json"):
        assert (tmp_path / "start" / name).read_text() == (tmp_path / "plain" / name).read_text()
    parser = build_parser()
    args = ["train", "--task", "t", "--agent", "a", "--dataset", "d", "--out", "o"]
    assert from_args(RunSettings, parser.parse_args([*args, "--eval-at-start"])).eval_at_start
    help_text = parser._subparsers._group_actions[0].choices["train"].format_help()
    assert "--eval-at-start" in help_text and "untrained agent" in help_text
