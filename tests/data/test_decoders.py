"""The frame-inflating helper processes (``rlu.data.store.decoders``): a batch's frames are the
same whoever inflates them, a bad frame in a helper's part is named as the caller names it, a
file replaced under its path is still read from the caller's file, a killed helper gives one
clear error and then fresh helpers, and a helper never outlives the process that started it."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rlu.data import DatasetWriter, Schema, make_episode, open_dataset
from rlu.data.store import decoders as D
from rlu.types import ArraySpec, DiscreteSpec, FormatError, RluError
from tests.data.test_inflate import frames

SCHEMA = Schema(ArraySpec((84, 84), "uint8"), DiscreteSpec((), "int64", 4), frame_stack=4,
                image_encoding="zlib")  # fmt: skip


@pytest.fixture
def helpers(monkeypatch):
    """One helper process for this test (whatever the machine's cores), closed after it."""
    monkeypatch.delenv("RLU_DECODERS", raising=False)
    dec = D.Decoders(1)
    monkeypatch.setattr(D, "_DECODERS", (os.getpid(), dec))
    yield dec
    dec.close()


def dataset(path: Path, n: int = 600) -> tuple[Path, np.ndarray]:
    f = frames(n, seed=3)
    with DatasetWriter(path, SCHEMA) as w:
        w.append(make_episode(f, np.zeros(n - 1, np.int64), np.zeros(n - 1), True))
    return path, np.concatenate([np.zeros((3, 84, 84), np.uint8), f])


def batch(n: int, seed: int = 0) -> np.ndarray:
    """Rows of 256 stacked transitions (5 adjacent frames each), as a uniform sampler asks."""
    start = np.random.default_rng(seed).integers(0, n - 5, 256)
    return start[:, None] + np.arange(5)


def test_the_helpers_give_the_callers_bytes(tmp_path, helpers):
    path, ref = dataset(tmp_path / "ds")
    col = open_dataset(path).column("observation")
    for seed in range(3):
        rows = batch(len(col), seed)
        assert np.array_equal(col.take(rows), ref[rows])
    sorted_rows = np.unique(batch(len(col), 9))
    assert np.array_equal(col.take(sorted_rows), ref[sorted_rows])
    # the helper inflated a share of every batch (about half: this thread the rest)
    asked = 3 * len(np.unique(batch(len(col)))) + len(sorted_rows)
    assert asked / 4 < helpers.frames < asked


def test_a_bad_frame_in_a_helpers_part_is_named(tmp_path, helpers):
    path, _ = dataset(tmp_path / "ds")
    steps = path / "steps"
    offsets = np.fromfile(steps / "observation.offsets.bin", "<i8")
    data = bytearray((steps / "observation.zlib").read_bytes())
    bad = 590  # the batch's last frames go to the helper
    data[int(offsets[bad]) + 2 : int(offsets[bad]) + 12] = bytes(10)
    (steps / "observation.zlib").write_bytes(bytes(data))
    col = open_dataset(path).column("observation")
    rows = np.unique(np.concatenate([batch(len(col)).ravel(), [bad]]))
    with pytest.raises(FormatError, match=f"observation.zlib: frame {bad} is not a zlib stream"):
        col.take(rows)
    assert helpers.frames == 0  # the helper's part held the bad frame: nothing of it was kept


def test_a_file_replaced_under_its_path_is_read_from_the_callers_file(tmp_path, helpers):
    path, ref = dataset(tmp_path / "ds")
    col = open_dataset(path).column("observation")
    col.take(np.arange(3))  # the caller's file is open
    zfile = path / "steps" / "observation.zlib"
    other = zfile.with_name("other")
    other.write_bytes(zfile.read_bytes()[::-1])  # another file, then renamed over the path
    os.replace(other, zfile)
    rows = batch(len(col))
    assert np.array_equal(col.take(rows), ref[rows])
    assert helpers.frames == 0  # the helper refused the other file; this thread read its own


def test_a_killed_helper_is_one_clear_error_then_fresh_helpers(tmp_path, helpers):
    path, ref = dataset(tmp_path / "ds")
    col = open_dataset(path).column("observation")
    proc = helpers.helpers[0][0]
    proc.kill()
    proc.wait()
    with pytest.raises(RluError, match=r"helper process \(pid \d+\) ended.*RLU_DECODERS=0"):
        D.Decoders.collect(helpers, 1)
    fresh = D.decoders()  # the dead one noticed: new helpers
    assert fresh is not helpers and fresh is not None and fresh.alive()
    try:
        rows = batch(len(col))
        assert np.array_equal(col.take(rows), ref[rows]) and fresh.frames > 0
    finally:
        fresh.close()


def test_a_helper_ends_with_the_process_that_started_it(tmp_path):
    path, _ = dataset(tmp_path / "ds")
    code = (
        "import os, sys, numpy as np\n"
        "from rlu.data import open_dataset\n"
        "from rlu.data.store import decoders as D\n"
        "D._DECODERS = (os.getpid(), D.Decoders(1))\n"
        f"col = open_dataset({str(path)!r}).column('observation')\n"
        "col.take(np.arange(0, 590, 2))\n"
        "assert D._DECODERS[1].frames > 0\n"
        "print(D._DECODERS[1].helpers[0][0].pid, flush=True)\n"
        "os._exit(0)\n"  # no clean-up: the helper must notice on its own
    )
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=root, env=env, timeout=120
    )
    assert out.returncode == 0, out.stderr
    pid = int(out.stdout.split()[-1])
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return  # already gone
    try:
        ready, _, _ = select.select([fd], [], [], 60)  # readable once it has ended
        if not ready:
            signal.pidfd_send_signal(fd, signal.SIGKILL)
        assert ready, f"helper {pid} still runs after its parent ended"
    finally:
        os.close(fd)
