"""Concurrent and killed writers: two ``rlu convert`` into one DEST, two ``rlu train`` into one
``--out``, a stale lock of a killed writer, and conversion's reader processes after ``kill -9``
of their parent. Real processes, held at a known point by a line on stdin (no sleeps); waits on
process exit use pidfds with a deadline."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rlu.data import open_dataset
from rlu.data.release import families as Fm
from rlu.data.validate import validate
from rlu.locks import LockBusy, OutputLock, lock_path
from rlu.training.runs import load_results
from tests.release.test_families import window_record

ROOT = Path(__file__).resolve().parents[2]
TASK = "control_suite/cartpole_swingup"

# A convert (the real CLI) whose writer stops at its first append until a line arrives on stdin;
# it prints the pids of its reader processes first.
HELD_CONVERT = r"""
import multiprocessing as mp, sys
from rlu.data.store import writer as W
real = W.DatasetWriter.append_columns
held = []
def hold(self, batch):
    if not held:
        held.append(1)
        print("held", *[p.pid for p in mp.active_children()], flush=True)
        sys.stdin.readline()
    return real(self, batch)
W.DatasetWriter.append_columns = hold
from rlu.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _shards(tmp: Path, n: int, records: int) -> list[Path]:
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        recs = []
        for _ in range(records):
            r = window_record(rng, 2, {"position": 3, "velocity": 2})
            r["action"] = np.clip(r["action"][:, :1], -1, 1)
            recs.append(r)
        path = tmp / "src" / f"train-{i:05d}-of-{n:05d}"
        path.parent.mkdir(exist_ok=True)
        Fm.write_shard(path, "dm_control_suite", recs)
        out.append(path)
    return out


def _convert_args(files: list[Path], out: Path, workers: int = 1) -> list[str]:
    return [
        "convert",
        "--family",
        "dm_control_suite",
        "--task",
        TASK,
        "--out",
        str(out),
        "--workers",
        str(workers),
        *map(str, files),
    ]


def _held(args: list[str]) -> tuple[subprocess.Popen, list[int]]:
    proc = subprocess.Popen(
        [sys.executable, "-c", HELD_CONVERT, *args],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    line = proc.stdout.readline()
    assert line.startswith("held"), (line, proc.stderr.read() if proc.poll() is not None else "")
    return proc, [int(p) for p in line.split()[1:]]


def _cli(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rlu", *args], cwd=ROOT, capture_output=True, text=True, timeout=300
    )


def _exited_within(pid: int, seconds: float) -> bool:
    """Whether process ``pid`` (not our child) ends within ``seconds``: a pidfd turns readable
    when it exits."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return True
    try:
        return bool(select.select([fd], [], [], seconds)[0])
    finally:
        os.close(fd)


def test_two_converts_into_one_dest(tmp_path):
    files = _shards(tmp_path, 2, 200)
    out = tmp_path / "ds"
    first, _ = _held(_convert_args(files, out))
    try:
        second = _cli(_convert_args(files, out))
        assert second.returncode == 2, second.stderr
        assert f"in use by PID {first.pid}" in second.stderr and "Traceback" not in second.stderr
        assert (tmp_path / ".ds.partial").is_dir()  # the first writer's work is untouched
    finally:
        first.stdin.write("\n")
        first.stdin.flush()
        first.stdin.close()
    assert first.wait(timeout=300) == 0, first.stderr.read()
    assert "wrote" in first.stdout.read()
    assert validate(out).ok and len(open_dataset(out, verify=True)) == 400
    assert not lock_path(out).exists() and not (tmp_path / ".ds.partial").exists()


def test_a_killed_writers_lock_is_taken_over(tmp_path):
    files = _shards(tmp_path, 1, 50)
    out = tmp_path / "ds"
    first, _ = _held(_convert_args(files, out))
    first.kill()
    first.wait(timeout=60)
    assert lock_path(out).exists() and (tmp_path / ".ds.partial").is_dir()  # stale leftovers
    again = _cli(_convert_args(files, out))
    assert again.returncode == 0, again.stderr
    assert validate(out).ok and not (tmp_path / ".ds.partial").exists()


def test_readers_die_with_their_killed_parent(tmp_path):
    files = _shards(tmp_path, 4, 3000)  # more than a pipe holds: readers block on their queues
    first, readers = _held(_convert_args(files, tmp_path / "ds", workers=2))
    assert readers, "the convert started no reader processes"
    try:
        os.kill(first.pid, signal.SIGKILL)
        first.wait(timeout=60)
        alive = [pid for pid in readers if not _exited_within(pid, 30)]
        assert not alive, f"reader processes {alive} outlived their parent"
    finally:
        for pid in readers:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_lock_in_process(tmp_path):
    target = tmp_path / "out"
    with OutputLock(target, "dataset"):
        with pytest.raises(LockBusy, match=rf"in use by PID {os.getpid()}"):
            OutputLock(target, "dataset").acquire()
    assert not lock_path(target).exists()
    with OutputLock(target):  # free again
        pass


def test_the_folders_a_lock_made_go_with_it_while_empty(tmp_path):
    """A lock creates the folders its file needs; released, it removes those still empty (and
    never one that was there before or that holds anything)."""
    (tmp_path / "kept").mkdir()
    with OutputLock(tmp_path / "kept" / "a" / "b" / "out"):
        assert (tmp_path / "kept" / "a" / "b").is_dir()
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["kept"]
    with OutputLock(tmp_path / "kept" / "a" / "b" / "out"):
        (tmp_path / "kept" / "a" / "b" / "out").mkdir()  # what the locked writer made
    assert (tmp_path / "kept" / "a" / "b" / "out").is_dir()
    with OutputLock(tmp_path / "kept" / "c" / "out"):
        (tmp_path / "kept" / "c" / "note").write_text("x")  # the inner folder holds a file
    assert (tmp_path / "kept" / "c" / "note").exists()


def test_a_train_refused_before_its_data_leaves_no_folder(tmp_path):
    """``rlu train`` whose dataset is missing: a clear error, and the run's parent folders
    that its lock made are gone again."""
    out = tmp_path / "runs" / "deep" / "run"
    failed = _cli(_train_args(str(tmp_path / "no_such_dataset"), out))
    assert failed.returncode == 2, failed.stderr
    assert "Traceback" not in failed.stderr and "no_such_dataset" in failed.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_stale_lock_file_of_a_dead_pid_is_taken_over(tmp_path):
    target = tmp_path / "out"
    lock_path(target).write_text("999999999\n")  # a pid that cannot be alive; nobody holds it
    with OutputLock(target) as lock:
        assert lock.held and lock_path(target).read_text().strip() == str(os.getpid())


# --- rlu train ------------------------------------------------------------------------------------
HELD_TRAIN = r"""
import sys
import tests.train.fake_agent as fa
real = fa.Agent.update
held = []
def hold(self, batch):
    if not held:
        held.append(1)
        print("held", flush=True)
        sys.stdin.readline()
    return real(self, batch)
fa.Agent.update = hold
from rlu.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.fixture(scope="module")
def pendulum(tmp_path_factory):
    pytest.importorskip("torch")
    pytest.importorskip("gymnasium")
    from tests.train.pendulum import write_dataset

    return str(write_dataset(tmp_path_factory.mktemp("p") / "pendulum", "test/pendulum", seed=0))


def _train_args(dataset: str, out: Path, task: str = "test/pendulum") -> list[str]:
    return [
        "train", "--task", task, "--agent", "tests.train.fake_agent", "--dataset", dataset,
        "--env", "tests.train.pendulum:make_env", "--steps", "6", "--eval-every", "-1",
        "--log-every", "2", "--checkpoint-every", "3", "--threads", "1", "--no-progress",
        "--out", str(out),
    ]  # fmt: skip


def test_two_trains_into_one_out(pendulum, tmp_path):
    out = tmp_path / "run"
    first = subprocess.Popen(
        [sys.executable, "-c", HELD_TRAIN, *_train_args(pendulum, out)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert first.stdout.readline().strip() == "held", first.stderr.read()
        second = _cli(_train_args(pendulum, out))
        assert second.returncode == 2 and f"in use by PID {first.pid}" in second.stderr
        assert "Traceback" not in second.stderr
    finally:
        first.stdin.write("\n")
        first.stdin.close()
    assert first.wait(timeout=300) == 0, first.stderr.read()
    assert (out / "result.json").exists() and not lock_path(out).exists()


def _files(folder: Path) -> dict[str, tuple[int, int, bytes]]:
    """Every file under ``folder``: (inode, mtime in ns, bytes), by relative path."""
    out = {}
    for path in sorted(folder.rglob("*")):
        if path.is_file():
            st = path.stat()
            out[str(path.relative_to(folder))] = (st.st_ino, st.st_mtime_ns, path.read_bytes())
    return out


def test_a_refused_resume_leaves_the_winner_an_uninterrupted_run(pendulum, tmp_path):
    """A run killed at its 5th update, then two ``--resume`` into its folder: the second, started
    while the first is held in its first update (folder written, logs cut back), is refused and
    touches no file; the winner's folder is then the uninterrupted run's, every file byte for
    byte (config.json, metrics/eval .jsonl and .csv, result.json, checkpoints: no field of them
    differs, none holds a wall-clock time)."""

    def args(out: Path) -> list[str]:
        return [*_train_args(pendulum, out), "--eval-every", "3", "--eval-episodes", "1",
                "--eval-envs", "1", "--eval-max-steps", "10", "--log-to", "csv"]  # fmt: skip

    reference, out = tmp_path / "reference", tmp_path / "run"
    assert _cli(args(reference)).returncode == 0
    killed = subprocess.run(
        [sys.executable, "-m", "rlu", *args(out)],
        cwd=ROOT,
        env={**os.environ, "RLU_TEST_SIGKILL_AT_UPDATE": "5"},
        capture_output=True,
    )
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    first = subprocess.Popen(
        [sys.executable, "-c", HELD_TRAIN, *args(out), "--resume"],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert first.stdout.readline().strip() == "held", first.stderr.read()
        before = _files(out)
        second = _cli([*args(out), "--resume"])
        assert second.returncode == 2 and f"in use by PID {first.pid}" in second.stderr
        assert "Traceback" not in second.stderr
        assert _files(out) == before, "the refused run touched the winner's folder"
    finally:
        first.stdin.write("\n")
        first.stdin.close()
    assert first.wait(timeout=300) == 0, first.stderr.read()
    won, ref = _files(out), _files(reference)
    assert sorted(won) == sorted(ref) and "checkpoints/step_00000006.pt" in won
    differ = [name for name in ref if won[name][2] != ref[name][2]]
    assert not differ, f"{differ} differ from the uninterrupted run's"


def test_a_train_failing_before_its_first_step_blocks_no_rerun(pendulum, tmp_path):
    out = tmp_path / "run"
    bad = _train_args(pendulum, out, task="control_suite/no_such_task")
    bad[bad.index("--env") : bad.index("--env") + 2] = []  # the registry's envs
    bad[bad.index("--eval-every") + 1] = "0"
    failed = _cli(bad)
    assert failed.returncode == 2 and "unknown task id" in failed.stderr
    assert not (out / "config.json").exists()
    rerun = _cli(_train_args(pendulum, out))
    assert rerun.returncode == 0, rerun.stderr


def test_a_killed_sweeps_workers_die_with_it(pendulum, tmp_path):
    fifo = tmp_path / "held"
    os.mkfifo(fifo)
    args = [
        "-m", "rlu", "sweep", "--tasks", "test/pendulum", "--agents", "tests.train.fake_agent",
        "--grid", "learning_rate=0.01", "--dataset", f"test/pendulum={pendulum}", "--seeds", "0",
        "1", "--workers", "2", "--steps", "6", "--eval-every", "-1",
        "--env", "tests.train.pendulum:make_env", "--out", str(tmp_path / "sweep"),
    ]  # fmt: skip
    env = {**os.environ, "RLU_TEST_HOLD_FIFO": str(fifo)}  # each worker hangs in its first update
    driver = subprocess.Popen([sys.executable, *args], cwd=ROOT, env=env, text=True,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)  # fmt: skip
    fd = os.open(fifo, os.O_RDWR)  # a writer of our own: no end-of-file between the workers'
    pids: list[int] = []
    try:
        text = ""
        while text.count("\n") < 2:
            assert select.select([fd], [], [], 300)[0], "the workers did not start"
            text += os.read(fd, 64).decode()
        pids = [int(p) for p in text.split()]
        os.kill(driver.pid, signal.SIGKILL)  # kill -9: no handler of the driver's runs
        driver.wait(timeout=60)
        alive = [pid for pid in pids if not _exited_within(pid, 30)]
        assert not alive, f"sweep workers {alive} outlived their killed driver"
        # nothing holds the runs' folders: the same sweep runs to the end
        rerun = _cli(args[2:])
        assert rerun.returncode == 0, rerun.stderr
        assert len(load_results(tmp_path / "sweep")) == 2
        assert "0: not evaluated, 1: not evaluated" in rerun.stdout  # --eval-every -1: no score
    finally:
        os.close(fd)
        driver.kill()
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_a_second_sweep_into_a_folder_in_use_is_refused_at_once(tmp_path):
    """Two ``rlu sweep`` into one --out: the second stops with "in use by PID N" before writing
    anything (on main both went on and both failed)."""
    from rlu.data.bundled import bundled_dataset

    out = tmp_path / "sweep"
    data = f"{TASK}={bundled_dataset()}"
    args = [sys.executable, "-m", "rlu", "sweep", "--tasks", TASK, "--agents", "bc",
            "--dataset", data, "--steps", "1", "--out", str(out)]  # fmt: skip
    with OutputLock(out, "sweep folder"):  # the first sweep, alive
        res = subprocess.run(args, cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 2, res.stderr
    assert f"in use by PID {os.getpid()}" in res.stderr and "Traceback" not in res.stderr
    assert not out.exists()


def test_a_second_export_to_one_file_is_refused_and_an_interrupt_in_a_close_is_kept(tmp_path):
    """Two ``rlu export`` to one file: the second stops with "in use" (on main both wrote the
    same temporary file and both exited 0). A Ctrl-C while an HDF5 file closes is raised after
    the close (h5py swallowed it, and the export exited 0)."""
    pytest.importorskip("h5py")
    from rlu.data.bundled import bundled_dataset
    from rlu.files import interrupts_deferred

    out = tmp_path / "d4rl.hdf5"
    args = [sys.executable, "-m", "rlu", "export", str(bundled_dataset()), "--format", "d4rl",
            "-o", str(out)]  # fmt: skip
    with OutputLock(out, "export file"):
        res = subprocess.run(args, cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 2 and "in use by PID" in res.stderr, res.stderr
    assert not out.exists() and not list(tmp_path.iterdir())
    done = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts_deferred():
            os.kill(os.getpid(), signal.SIGINT)
            done.append("the block ran to its end")
    assert done == ["the block ran to its end"]
