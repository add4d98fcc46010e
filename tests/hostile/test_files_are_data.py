"""Hostile files, round two: a name in a file never runs code, a planted link is never written
through, and rlu never deletes what it did not write.

Each case was seen on main before its fix: a run folder's config.json naming ``os:system`` as its
env factory ran a shell command under ``rlu evaluate``; a module path as a run's or a behaviour
policy's agent was imported; a lock file planted as a symlink received the PID; the quick start
deleted its ``--out`` (the dataset itself, or a folder it had not written) before it failed.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
ENV = "tests.train.pendulum:make_env"
AGENT = "tests.train.fake_agent"


def _rlu(*args: str, probe: str = "") -> subprocess.CompletedProcess:
    """``rlu ARGS`` in a fresh interpreter; ``probe``: a module whose presence in sys.modules
    after the command is printed on the last line of stdout."""
    code = (
        "import sys\nfrom rlu.cli import main\nrc = main(sys.argv[1:])\n"
        f"print('imported:', {probe!r} in sys.modules)\nsys.exit(rc)"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", code, *args], cwd=ROOT, env=env,
                          capture_output=True, text=True)  # fmt: skip


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A finished run of the fake agent in the test pendulum (the real loop)."""
    pytest.importorskip("torch")
    pytest.importorskip("gymnasium")
    from rlu.training.train import train
    from tests.fakes import train_config
    from tests.train.pendulum import write_dataset

    root = tmp_path_factory.mktemp("trained")
    data = write_dataset(root / "data", "test/pendulum", episodes=4)
    cfg = train_config(task="test/pendulum", agent=AGENT, dataset=str(data), steps=3,
                       eval_every=-1, checkpoint_every=3, env=ENV)  # fmt: skip
    train(cfg, root / "run")
    return root / "run"


def _tampered(run: Path, dest: Path, edit) -> Path:
    shutil.copytree(run, dest)
    config = json.loads((dest / "config.json").read_text())
    edit(config)
    (dest / "config.json").write_text(json.dumps(config))
    return dest


def test_an_env_factory_named_in_a_run_folder_is_never_called(trained, tmp_path):
    victim = tmp_path / "pwned"

    def edit(config):
        config["train"]["run"]["env"] = "os:system"
        config["train"]["task"] = f"touch {victim}"

    run = _tampered(trained, tmp_path / "run", edit)
    res = _rlu("evaluate", str(run), "--episodes", "1", "--agent", AGENT)
    assert res.returncode == 2, res.stderr
    assert not victim.exists()
    assert "names the env factory 'os:system'" in res.stderr
    assert "a module named in a file is never imported" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1  # one line, no traceback


def test_an_agent_module_named_in_a_run_folder_is_never_imported(trained, tmp_path):
    def edit(config):
        config["train"]["agent"] = "http.server"

    run = _tampered(trained, tmp_path / "run", edit)
    res = _rlu("evaluate", str(run), "--episodes", "1", "--env", ENV, probe="http.server")
    assert res.returncode == 2, res.stderr
    assert res.stdout.strip().splitlines()[-1] == "imported: False"
    assert "'http.server' is not one of rlu's continuous agents" in res.stderr
    assert "--agent http.server" in res.stderr  # the fix, for a module the user trusts


def test_a_run_of_a_trusted_module_evaluates_when_the_user_names_it(trained):
    res = _rlu("evaluate", str(trained), "--episodes", "1", "--env", ENV, "--agent", AGENT)
    assert res.returncode == 0, res.stderr
    assert "1 episodes: mean return" in res.stdout


def test_an_agent_module_named_in_a_behaviour_policy_is_never_imported(tmp_path):
    pytest.importorskip("torch")
    from rlu.data.bundled import bundled_dataset

    data = tmp_path / "data"
    shutil.copytree(bundled_dataset(), data)
    meta_path = data / "policies" / "run_000" / "checkpoint_00000.json"
    meta = json.loads(meta_path.read_text())
    meta["agent"] = "http.server"
    meta_path.write_text(json.dumps(meta))
    manifest = json.loads((data / "manifest.json").read_text())  # a consistent forgery
    entry = manifest["files"]["policies/run_000/checkpoint_00000.json"]
    entry["sha256"] = hashlib.sha256(meta_path.read_bytes()).hexdigest()
    entry["bytes"] = meta_path.stat().st_size
    (data / "manifest.json").write_text(json.dumps(manifest))
    res = _rlu("evaluate-behaviour", str(data), "--run", "0", "--checkpoint", "0",
               "--episodes", "1", probe="http.server")  # fmt: skip
    assert res.returncode == 2, res.stderr
    assert res.stdout.strip().splitlines()[-1] == "imported: False"
    assert "http.server" in res.stderr and "never imported" in res.stderr


def test_a_lock_file_planted_as_a_symlink_is_not_written_through(tmp_path):
    from rlu.locks import OutputLock, lock_path
    from rlu.types import RluError

    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    target = tmp_path / "run"
    os.symlink(victim, lock_path(target))
    with pytest.raises(RluError, match="is a symbolic link; rlu does not write through it"):
        OutputLock(target, "run folder").acquire()
    assert victim.read_text() == "precious\n"
    hard = tmp_path / "other"
    os.link(victim, lock_path(hard))
    with pytest.raises(RluError, match="not a plain file of its own"):
        OutputLock(hard, "run folder").acquire()
    assert victim.read_text() == "precious\n"


def test_a_planted_temporary_file_is_not_written_through(tmp_path):
    from rlu.files import write_json

    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    target = tmp_path / "config.json"
    os.symlink(victim, target.with_name(f".{target.name}.{os.getpid()}.tmp"))
    # temporaries have unpredictable names: a link planted at a guessable one is left alone
    write_json(target, {"ok": 1})
    assert victim.read_text() == "precious\n" and json.loads(target.read_text()) == {"ok": 1}
    assert target.with_name(f".{target.name}.{os.getpid()}.tmp").is_symlink()


def test_convert_never_replaces_a_folder_that_is_not_its_dataset(tmp_path):
    from rlu.data import DatasetWriter, Schema
    from rlu.types import ArraySpec, BoundedSpec, RluError

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    schema = Schema(ArraySpec((2,), "float32"), BoundedSpec((1,), "float32"))
    with pytest.raises(RluError, match="is not an rlu dataset"):
        DatasetWriter(mine, schema, overwrite=True)
    assert (mine / "notes.txt").read_text() == "mine"
    res = _rlu("convert", "--family", "dm_control_suite", "--task",
               "control_suite/cartpole_swingup", "--overwrite", "--out", str(tmp_path),
               str(mine / "notes.txt"))  # fmt: skip
    assert res.returncode == 2 and "could destroy it" in res.stderr
    assert (mine / "notes.txt").read_text() == "mine"


def test_train_never_writes_into_a_folder_that_is_not_a_run(tmp_path):
    pytest.importorskip("torch")
    from tests.train.pendulum import write_dataset

    data = write_dataset(tmp_path / "data", "test/pendulum", episodes=4)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    args = ["train", "--task", "test/pendulum", "--agent", AGENT, "--dataset", str(data),
            "--env", ENV, "--steps", "2", "--eval-every", "-1", "--no-progress"]  # fmt: skip
    res = _rlu(*args, "--out", str(mine))
    assert res.returncode == 2 and "is not an rlu run folder" in res.stderr, res.stderr
    res = _rlu(*args, "--out", str(data / "run"))
    assert res.returncode == 2 and "could destroy it" in res.stderr, res.stderr
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
