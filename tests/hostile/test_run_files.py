"""Hostile run and sweep files, and option values: every one is a one-line error (exit 2) naming
the file or the option, never a traceback (each was a traceback or silently accepted on main)."""

from __future__ import annotations

import json
import os
import shutil
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


def _one_line_error(res: subprocess.CompletedProcess, *says: str) -> None:
    assert res.returncode == 2, (res.returncode, res.stderr)
    lines = [x for x in res.stderr.strip().splitlines() if not x.startswith("rlu train: ")]
    assert "Traceback" not in res.stderr and len(lines) == 1, res.stderr
    for text in says:
        assert text in lines[0], lines[0]


@pytest.fixture(scope="module")
def bc_run(tmp_path_factory):
    """Two BC runs (the real agent, the bundled data): 4 steps, checkpoints at 2 and 4."""
    pytest.importorskip("torch")
    from rlu.data.bundled import bundled_dataset

    root = tmp_path_factory.mktemp("bc")
    for agent in ("bc", "d4pg"):
        res = _rlu("train", "--task", TASK, "--agent", agent, "--dataset",
                   str(bundled_dataset()), "--steps", "4", "--checkpoint-every", "2",
                   "--eval-every", "-1", "--no-progress", "--out", str(root / agent),
                   "batch_size=8")  # fmt: skip
        assert res.returncode == 0, res.stderr
    return root


def _copy(src: Path, dest: Path) -> Path:
    shutil.copytree(src, dest)
    return dest


@pytest.mark.parametrize(
    ("edit", "says"),
    [
        (lambda c: {}, "field 'train' is missing"),
        (lambda c: [c], "expected an object"),
        (lambda c: {**c, "action_spec": {**c["action_spec"], "shape": [-1]}},
         "field 'action_spec.shape[0]' is -1"),
        (lambda c: {**c, "agent_config": {**c["agent_config"], "hidden_size": "wide"}},
         "field 'hidden_size' is a string"),
        (lambda c: {**c, "agent_config": {**c["agent_config"], "hidden_size": 10**6}},
         "field 'hidden_size' is 1000000; expected an integer from 1 to"),
        (lambda c: {**c, "train": {**c["train"], "seed": -3}}, "field 'train.seed' is -3"),
        (lambda c: json.loads("[" * 5000 + "]" * 5000), "nested too deep"),
    ],
    ids=["empty", "list", "negative_shape", "string_width", "million_units", "negative_seed",
         "deep"],
)  # fmt: skip
def test_a_damaged_run_config_is_one_line(bc_run, tmp_path, edit, says):
    run = _copy(bc_run / "bc", tmp_path / "run")
    config = json.loads((run / "config.json").read_text())
    try:
        text = json.dumps(edit(config))
    except RecursionError:
        text = "[" * 5000 + "]" * 5000
    (run / "config.json").write_text(text)
    _one_line_error(_rlu("evaluate", str(run), "--episodes", "1"), "config.json", says)


def test_another_agents_checkpoint_is_one_line(bc_run, tmp_path):
    run = _copy(bc_run / "bc", tmp_path / "run")
    theirs = bc_run / "d4pg" / "checkpoints" / "step_00000004.pt"
    shutil.copy(theirs, run / "checkpoints" / "step_00000004.pt")
    _one_line_error(_rlu("evaluate", str(run), "--episodes", "1"), "step_00000004.pt",
                    "does not fit the agent")  # fmt: skip


def test_garbage_generator_state_on_resume_is_one_line(bc_run, tmp_path):
    import torch

    from rlu.data.bundled import bundled_dataset

    run = _copy(bc_run / "bc", tmp_path / "run")
    (run / "result.json").unlink()
    ckpt = run / "checkpoints" / "step_00000002.pt"
    (run / "checkpoints" / "step_00000004.pt").unlink()
    state = torch.load(ckpt, weights_only=True)
    state["numpy_rng"] = ["MT19937", [1, 2, 3], "x", 0, 0.0]
    torch.save(state, ckpt)
    args = ["train", "--task", TASK, "--agent", "bc", "--dataset", str(bundled_dataset()),
            "--steps", "4", "--checkpoint-every", "2", "--eval-every", "-1", "--no-progress",
            "--out", str(run), "--resume", "batch_size=8"]  # fmt: skip
    _one_line_error(_rlu(*args), "step_00000002.pt", "generator state is damaged")
    state["numpy_rng"], state["step"] = [], 10**9
    torch.save(state, ckpt)
    _one_line_error(_rlu(*args), "step_00000002.pt", "entry 'step'")


def test_a_log_torn_in_the_middle_is_one_line(bc_run, tmp_path):
    from rlu.data.bundled import bundled_dataset

    run = _copy(bc_run / "bc", tmp_path / "run")
    (run / "result.json").unlink()
    (run / "checkpoints" / "step_00000004.pt").unlink()
    lines = (run / "metrics.jsonl").read_text().splitlines()
    (run / "metrics.jsonl").write_text('{"step": 1, "loss"\n' + "\n".join(lines) + "\n")
    res = _rlu("train", "--task", TASK, "--agent", "bc", "--dataset", str(bundled_dataset()),
               "--steps", "4", "--checkpoint-every", "2", "--eval-every", "-1",
               "--no-progress", "--out", str(run), "--resume", "batch_size=8")  # fmt: skip
    _one_line_error(res, "metrics.jsonl: line 1", "not valid JSON")


def test_damaged_sweep_files_are_one_line_in_the_report(tmp_path):
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "sweep.json").write_text(json.dumps({"datasets": {"t": "/d"}}))
    good = {"task": "control_suite/cartpole_swingup", "agent": "bc", "config": "default",
            "seed": 0, "score": 1.0, "run": "r"}  # fmt: skip
    for bad, says in [
        ({**good, "seed": "zero"}, "line 1: field 'seed' is a string"),
        ({**good, "score": [1]}, "line 1: field 'score' is a list"),
        ([good], "line 1 is a list"),
    ]:
        (sweep / "results.jsonl").write_text(json.dumps(bad) + "\n")
        _one_line_error(_rlu("report", str(sweep)), "results.jsonl", says)
    (sweep / "results.jsonl").write_text(json.dumps(good) + "\n")
    (sweep / "sweep.json").write_text("[]")
    _one_line_error(_rlu("report", str(sweep)), "sweep.json", "expected an object")
    (sweep / "sweep.json").write_text(json.dumps({"datasets": {"t": "/d"}}))
    (sweep / "fqe.json").write_text(json.dumps({"selections": 3}))
    _one_line_error(_rlu("report", str(sweep)), "fqe.json", "field 'selections' is an integer")


@pytest.mark.parametrize(
    "args",
    [
        ["train", "--task", TASK, "--agent", "bc", "--dataset", "d", "--out", "o",
         "--checkpoint-every", "0"],
        ["train", "--task", TASK, "--agent", "bc", "--dataset", "d", "--out", "o",
         "--log-every", "0"],
        ["train", "--task", TASK, "--agent", "bc", "--dataset", "d", "--out", "o", "--seed", "-1"],
        ["train", "--task", TASK, "--agent", "bc", "--dataset", "d", "--out", "o", "--steps", "0"],
        ["train", "--task", TASK, "--agent", "bc", "--dataset", "d", "--out", "o",
         "--eval-envs", "0"],
        ["train", "--task", TASK, "--agent", "bc", "--dataset", "d", "--out", "o",
         "--threads", "0"],
        ["evaluate", "run", "--envs", "0"],
        ["evaluate-behaviour", "d", "--fqe-target-period", "0"],
        ["sweep", "--tasks", TASK, "--agents", "bc", "--dataset", f"{TASK}=d", "--out", "o",
         "--steps", "-1"],
    ],
    ids=["checkpoint_every", "log_every", "seed", "steps", "eval_envs", "threads", "envs",
         "fqe_target_period", "sweep_steps"],
)  # fmt: skip
def test_option_values_out_of_range_are_refused_by_the_parser(args):
    res = _rlu(*args)
    assert res.returncode == 2 and "is out of range" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr


def test_overrides_of_the_wrong_type_name_the_field(tmp_path):
    from rlu.data.bundled import bundled_dataset

    base = ["train", "--task", TASK, "--agent", "bc", "--dataset", str(bundled_dataset()),
            "--out", str(tmp_path / "o"), "--steps", "1", "--eval-every", "-1"]  # fmt: skip
    _one_line_error(_rlu(*base, "learning_rate=abc"), "field 'learning_rate' is a string")
    _one_line_error(_rlu(*base, "batch_size=1e9"), "'batch_size' is 1000000000", "from 1 to")
    _one_line_error(_rlu(*base, "--agent", "os.path"), "'os.path' has no Config")
    _one_line_error(_rlu(*base, "--task", "atari/Pong"), "holds data of task", TASK)
    assert not (tmp_path / "o").exists()
