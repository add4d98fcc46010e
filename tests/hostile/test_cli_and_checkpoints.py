"""The CLI on hostile input (one line on stderr, the documented exit code, never a traceback),
a closed output pipe, and damaged or planted checkpoints."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from rlu.cli import EXIT_CODES, main
from rlu.types import FormatError, RluError
from tests.hostile.test_store_corpus import CASES as STORE_CASES
from tests.hostile.test_store_corpus import FIFO

ROOT = Path(__file__).resolve().parents[2]


def _rlu(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rlu", *args], cwd=ROOT, capture_output=True, timeout=300, **kw
    )


@pytest.mark.parametrize("command", [["list"], ["list", "--json"], ["info", "atari/Pong"]])
def test_closed_pipe_is_quiet(command):
    r, w = os.pipe()
    os.close(r)  # nobody will ever read: the first write fails with EPIPE
    try:
        out = subprocess.run(
            [sys.executable, "-m", "rlu", *command],
            cwd=ROOT,
            stdout=w,
            stderr=subprocess.PIPE,
            timeout=120,
        )
    finally:
        os.close(w)
    assert out.returncode == 141 and out.stderr == b"", out.stderr.decode()


def test_list_into_head():
    out = subprocess.run(
        f"{sys.executable} -m rlu list --json | head -1; exit ${{PIPESTATUS[0]}}",
        shell=True,
        executable="/bin/bash",
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.stdout == "[\n" and out.returncode in (0, 141) and out.stderr == "", out.stderr


@pytest.mark.parametrize("name", sorted(set(STORE_CASES) - FIFO))
def test_validate_and_info_on_the_store_corpus(name, tmp_path, capsys):
    c = STORE_CASES[name](tmp_path)
    assert main(["validate", str(c.ds)]) == 1
    out = capsys.readouterr()
    assert "FAIL" in out.out and c.file in out.out
    code = main(["info", str(c.ds)])
    err = capsys.readouterr().err
    assert code in (0, 2) and (code == 0 or err.startswith("rlu: error: ")), err


def test_exit_codes_are_documented(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    assert all(str(code) in text for code in EXIT_CODES)
    with pytest.raises(SystemExit) as info:  # argparse: a usage error is 2 as well
        main(["convert"])
    assert info.value.code == 2


def test_unwritable_output_is_one_line(tmp_path, capsys):
    from rlu.data import Schema, open_dataset
    from rlu.data.d4rl import export_d4rl
    from rlu.data.synthetic import write_synthetic
    from rlu.tasks import get_task

    task = "control_suite/cartpole_swingup"
    src = write_synthetic(tmp_path / "src", Schema.for_task(get_task(task)), 2, 4)
    npz = export_d4rl(open_dataset(src), tmp_path / "x.npz")
    (tmp_path / "file").write_text("a file: nothing can be created under it")
    out = tmp_path / "file" / "ds"
    code = main(["import", str(npz), "--format", "d4rl", "--task", task, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("rlu: error: ") and err.count("\n") == 1, err


# --- checkpoints ----------------------------------------------------------------------------------
class Planted:
    """Unpickling this would create ``marker``: proof that the payload ran."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    pytest.importorskip("torch")
    pytest.importorskip("gymnasium")
    from rlu.training.train import train
    from tests.fakes import train_config
    from tests.train.pendulum import write_dataset

    root = tmp_path_factory.mktemp("ck")
    dataset = write_dataset(root / "pendulum", "test/pendulum", seed=0)
    cfg = train_config(
        task="test/pendulum",
        agent="tests.train.fake_agent",
        dataset=str(dataset),
        steps=4,
        eval_every=-1,
        checkpoint_every=2,
        log_every=2,
        env="tests.train.pendulum:make_env",
        torch_threads=1,
    )
    train(cfg, root / "run")
    return root / "run", cfg


def _damage(ckpt: Path, how: str, marker: Path) -> None:
    import torch

    data = ckpt.read_bytes()
    if how == "python_object":
        state = torch.load(ckpt, weights_only=True)
        state["agent"]["extra"] = Planted(str(marker))
        torch.save(state, ckpt)
    elif how == "empty":
        ckpt.write_bytes(b"")
    elif how == "truncated":
        ckpt.write_bytes(data[: len(data) // 2])
    elif how == "junk":
        ckpt.write_bytes(b"not a checkpoint at all " * 40)
    elif how == "a_tensor":
        torch.save(torch.zeros(3), ckpt)
    elif how == "no_agent":
        state = torch.load(ckpt, weights_only=True)
        del state["agent"]
        torch.save(state, ckpt)


HOW = ["python_object", "empty", "truncated", "junk", "a_tensor", "no_agent"]


@pytest.mark.parametrize("how", HOW)
def test_damaged_checkpoint(run, tmp_path, how, capsys):
    import shutil

    from rlu.training.checkpoints import load_state as load_checkpoint
    from rlu.training.train import train

    path, cfg = run
    copy = tmp_path / "run"
    shutil.copytree(path, copy)
    ckpt = copy / "checkpoints" / "step_00000004.pt"
    marker = tmp_path / "PAYLOAD_RAN"
    _damage(ckpt, how, marker)
    with pytest.raises(FormatError) as info:
        load_checkpoint(ckpt, ("agent",))
    msg = str(info.value)
    assert str(ckpt) in msg and "weights_only" not in msg, msg
    # the commands that read checkpoints: evaluate (one line, exit 2) and resume
    code = main(["evaluate", str(ckpt), "--episodes", "1", "--envs", "1",
                 "--env", "tests.train.pendulum:make_env"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and str(ckpt) in err and "weights_only" not in err, err
    (copy / "result.json").unlink()
    with pytest.raises(RluError, match="step_00000004.pt"):
        train(cfg, copy, resume=True)
    assert not marker.exists()


def test_a_command_started_with_stdout_closed_ends_without_a_traceback():
    root = Path(__file__).resolve().parents[2]
    for args in (["list"], ["info", "control_suite/cartpole_swingup"]):
        res = subprocess.run(
            [sys.executable, "-m", "rlu", *args],
            cwd=root,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=lambda: os.close(1),
        )
        assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
