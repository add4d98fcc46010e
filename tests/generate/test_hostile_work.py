"""Hostile generation work folders and concurrent generations: a damaged ``settings.json`` or
``state.pt`` (garbage, a list, truncated, pickled code, another shape) is a one-line error naming
the file and the fix, never torch's traceback or its advice to load with ``weights_only=False``;
two ``rlu generate`` into one ``--out``: one winner, the other refused with "in use by PID N";
settings out of range are refused before anything runs."""

from __future__ import annotations

import os
import pickle
import select
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rlu.types import ConfigError, FormatError, RluError

ROOT = Path(__file__).resolve().parents[2]
TASK = "control_suite/cartpole_swingup"


def _config(task: str = TASK):
    from rlu.generate import GenerateConfig

    return GenerateConfig(task, scale="tiny", runs=1, seed=7, progress=False)


class _Stop(Exception):
    pass


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory) -> Path:
    """The work folder of a tiny generation stopped after run 0's first chunk (its state.pt
    saved, the run not done)."""
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    from rlu.generate import generate

    root = tmp_path_factory.mktemp("interrupted")

    def stop(run: int, chunk: int) -> None:
        raise _Stop

    with pytest.raises(_Stop):
        generate(_config(), root / "d", on_chunk=stop)
    work = root / ".d.generate"
    assert (work / "run_000" / "state.pt").is_file()
    return work


def _resume_with(interrupted: Path, tmp_path: Path, damage) -> str:
    """Copy the interrupted work folder, ``damage(work)`` it, resume: the error's text."""
    from rlu.generate import generate

    work = tmp_path / ".d.generate"
    shutil.copytree(interrupted, work)
    damage(work)
    with pytest.raises(RluError) as err:
        generate(_config(), tmp_path / "d")
    text = str(err.value)
    assert "\n" not in text and "weights_only" not in text and "Traceback" not in text, text
    assert not (tmp_path / "d").exists()
    return text


def _edit_state(edit):
    def damage(work: Path) -> None:
        import torch

        path = work / "run_000" / "state.pt"
        state = torch.load(path, weights_only=True)
        edit(state)
        torch.save(state, path)

    return damage


def _write(rel: str, data: bytes):
    def damage(work: Path) -> None:
        (work / rel).write_bytes(data)

    return damage


STATE = "run_000/state.pt"
CODE = pickle.dumps(os.system, protocol=2)  # a pickle that would call os.system


@pytest.mark.parametrize(
    "name,damage,says",
    [
        ("garbage", _write(STATE, b"\x00not a torch file" * 64), "truncated or not a torch"),
        ("empty", _write(STATE, b""), "empty file"),
        ("pickled code", _write(STATE, CODE), "holds Python objects"),
    ],
)
def test_a_damaged_state_file_is_one_line_naming_it(interrupted, tmp_path, name, damage, says):
    text = _resume_with(interrupted, tmp_path, damage)
    assert f"{tmp_path / '.d.generate' / STATE}:" in text and says in text, text
    assert "remove" in text  # the fix


def test_a_truncated_or_list_state_file_is_refused(interrupted, tmp_path):
    import torch

    real = (interrupted / "run_000" / "state.pt").read_bytes()
    text = _resume_with(interrupted, tmp_path / "a", _write(STATE, real[: len(real) // 2]))
    assert "truncated or not a torch" in text
    text = _resume_with(
        interrupted, tmp_path / "b", lambda w: torch.save([1, 2, 3], w / "run_000" / "state.pt")
    )
    assert "holds a list, not a state dict" in text


@pytest.mark.parametrize(
    "edit,says",
    [
        (lambda st: st.__setitem__("agent", {"nope": 1}), "agent state does not fit"),
        (lambda st: st.pop("rng"), "no ['rng'] entries"),
        (lambda st: st.__setitem__("rng", {"bit_generator": "PCG64"}), "random generator"),
        (lambda st: st.__setitem__("episode", -3), "entry 'episode' is -3"),
        (lambda st: st.__setitem__("done", "yes"), "entry 'done'"),
        (lambda st: st.__setitem__("replay", [1]), "the replay's state"),
        (
            lambda st: st["replay"]["arrays"].__setitem__("reward", st["replay"]["arrays"]["next"]),
            "the replay's entry 'reward' is int64",
        ),
        (
            lambda st: st["replay"]["arrays"]["next"].add_(10**9),
            "'next' holds rows outside the ring",
        ),
    ],
)
def test_a_state_of_another_shape_is_refused(interrupted, tmp_path, edit, says):
    text = _resume_with(interrupted, tmp_path, _edit_state(edit))
    assert says in text and "state.pt" in text, text


@pytest.mark.parametrize("data,says", [(b"{not json", "not valid JSON"), (b"[1, 2]", "is a list")])
def test_a_damaged_settings_file_is_refused(interrupted, tmp_path, data, says):
    text = _resume_with(interrupted, tmp_path, _write("settings.json", data))
    assert "settings.json" in text and says in text and "start the generation afresh" in text


def test_the_cli_says_it_in_one_line(interrupted, tmp_path, capsys):
    from rlu.cli import main

    shutil.copytree(interrupted, tmp_path / ".d.generate")
    (tmp_path / ".d.generate" / STATE).write_bytes(b"garbage")
    argv = ["generate", TASK, "--scale", "tiny", "--seeds", "1", "--seed", "7", "--no-progress"]
    assert main([*argv, "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("rlu: error: ") and "state.pt" in err[0]


def test_rwrl_snapshot_files_are_read_back_checked(tmp_path):
    torch = pytest.importorskip("torch")
    from rlu.generate import rwrl

    run_dir = tmp_path / "run_000"
    run_dir.mkdir()
    path = run_dir / "snapshots.pt"
    path.write_bytes(b"garbage")
    with pytest.raises(FormatError, match="snapshots.pt: it is truncated"):
        rwrl._load_history(path, run_dir)
    torch.save({0: "not a pair"}, path)
    with pytest.raises(FormatError, match="chunk 0's entry is not"):
        rwrl._load_history(path, run_dir)
    torch.save({"chunk": 1, "return": 1.0, "converged": 2.0, "agent": {"x": 1}}, path)
    with pytest.raises(FormatError, match="agent state does not fit"):
        rwrl._load_snapshot(path, torch.nn.Linear(1, 1))


# --- settings out of range ------------------------------------------------------------------
def test_settings_out_of_range_are_refused_before_anything_runs(tmp_path, capsys):
    from rlu.cli import main
    from rlu.generate import GenerateConfig
    from rlu.generate.online import OnlineConfig

    with pytest.raises(
        ConfigError, match="field 'checkpoint_steps' is 0; expected an integer from 1 to"
    ):
        OnlineConfig("d4pg", episodes=2, checkpoint_steps=0)
    with pytest.raises(ConfigError, match="field 'chunk_episodes'"):
        OnlineConfig("d4pg", episodes=2, chunk_episodes=0)
    with pytest.raises(ConfigError, match="field 'runs' is 0"):
        GenerateConfig(TASK, runs=0)
    with pytest.raises(ConfigError, match="field 'seed' is -1"):
        GenerateConfig(TASK, seed=-1)
    with pytest.raises(ConfigError, match="field 'scale'"):
        GenerateConfig(TASK, scale="huge")
    for flags in (["--seeds", "0"], ["--seed", "-1"], ["--workers", "0"], ["--scale", "huge"]):
        with pytest.raises(SystemExit) as exit_:
            main(["generate", TASK, "--out", str(tmp_path / "x"), *flags])
        assert exit_.value.code == 2, flags
    assert "out of range" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_an_existing_out_is_refused_before_anything_runs(tmp_path):
    from rlu.generate import generate

    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("my data")
    with pytest.raises(RluError, match="already exists; rlu generate writes a new dataset"):
        generate(_config(), tmp_path / "mine")
    (tmp_path / "rw").mkdir()
    (tmp_path / "rw" / "notes.txt").write_text("my data")
    with pytest.raises(RluError, match="not an interrupted rlu generate of RWRL"):
        generate(_config("rwrl/cartpole_swingup"), tmp_path / "rw")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "rw"]  # nothing written
    assert (tmp_path / "mine" / "notes.txt").read_text() == "my data"


# --- two generations into one --out ---------------------------------------------------------
# A generate (the real CLI) held once it has claimed the work folder, until a line on stdin.
HELD = r"""
import sys
from rlu.generate import common
real = common.open_work
def held(*args, **kw):
    real(*args, **kw)
    print("held", flush=True)
    sys.stdin.readline()
common.open_work = held
from rlu.generate import recipe
recipe.open_work = held
from rlu.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _wait(proc: subprocess.Popen, seconds: float) -> int:
    """The exit status of ``proc``, waiting at most ``seconds`` (a pidfd: no polling loop)."""
    fd = os.pidfd_open(proc.pid)
    try:
        ready, _, _ = select.select([fd], [], [], seconds)
    finally:
        os.close(fd)
    if not ready:
        proc.kill()
        pytest.fail(f"process {proc.pid} did not finish within {seconds} s")
    return proc.wait()


def test_two_generations_into_one_out_have_one_winner(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    from rlu.data.validate import validate

    out = tmp_path / "d"
    args = ["generate", TASK, "--scale", "tiny", "--seeds", "1", "--seed", "7", "--no-progress"]
    args += ["--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    first = subprocess.Popen(
        [sys.executable, "-c", HELD, *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert first.stdout.readline().strip() == "held"
        second = subprocess.run(
            [sys.executable, "-m", "rlu", *args], capture_output=True, text=True, env=env
        )
        assert second.returncode == 2, second.stderr
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and f"in use by PID {first.pid}" in lines[0], lines
        first.stdin.write("go\n")
        first.stdin.flush()
        assert _wait(first, 900) == 0, first.stderr.read()[-2000:]
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert validate(out).ok
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]  # no work folder, no lock left
