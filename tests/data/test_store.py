"""The episode store: round trips, atomic writes under SIGKILL, and clear errors on bad input."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rlu.data import DatasetWriter, Schema, make_episode, open_dataset
from rlu.data.synthetic import random_episodes, write_synthetic
from rlu.tasks import get_task
from rlu.types import FormatError, RluError, SpecError

CARTPOLE = Schema.for_task(get_task("control_suite/cartpole_swingup"))
LOCO = Schema.for_task(get_task("locomotion/rodent_gaps"), image_encoding="zlib")
ATARI = Schema.for_task(get_task("atari/Pong"), image_encoding="zlib")


@pytest.mark.parametrize("schema", [CARTPOLE, LOCO, ATARI], ids=["control", "camera", "atari"])
def test_round_trip_every_segment(tmp_path, schema):
    segs = list(random_episodes(schema, 4, 6, seed=1, vary_length=True))
    with DatasetWriter(tmp_path / "ds", schema, {"source": "test"}) as w:
        for s in segs:
            w.append(s)
    ds = open_dataset(tmp_path / "ds", verify=True)
    assert len(ds) == 4 and ds.num_steps == sum(len(s) for s in segs)
    assert ds.manifest["counts"]["episodes"] == 4
    for want, got in zip(segs, ds.segments(), strict=True):
        if isinstance(want.observation, dict):
            for k in want.observation:
                np.testing.assert_array_equal(got.observation[k], want.observation[k])
        else:
            np.testing.assert_array_equal(got.observation, want.observation)
        for f in ("action", "reward", "discount", "is_first", "is_last", "is_terminal"):
            np.testing.assert_array_equal(getattr(got, f), getattr(want, f))
        assert got.metadata["episode_id"] == want.metadata["episode_id"]
        assert got.metadata["episode_return"] == pytest.approx(want.metadata["episode_return"])


@pytest.mark.parametrize("schema", [CARTPOLE, LOCO, ATARI], ids=["control", "camera", "atari"])
def test_appending_datasets_writes_the_bytes_of_their_segments(tmp_path, schema):
    """append_dataset (how a cluster job assembles its parts): the same files as appending
    every segment of the parts to one writer, frame-stacked and zlib columns included."""
    segs = list(random_episodes(schema, 7, 5, seed=2, vary_length=True))
    with DatasetWriter(tmp_path / "whole", schema, {"source": "test"}) as w:
        for s in segs:
            w.append(s)
    for name, part in (("a", segs[:3]), ("b", segs[3:4]), ("c", segs[4:])):
        with DatasetWriter(tmp_path / name, schema) as w:
            w.extend(part)
    seen = []
    with DatasetWriter(tmp_path / "joined", schema, {"source": "test"}) as w:
        for name in "abc":
            w.append_dataset(tmp_path / name, on_bytes=seen.append)
    whole = json.loads((tmp_path / "whole" / "manifest.json").read_text())
    joined = json.loads((tmp_path / "joined" / "manifest.json").read_text())
    assert whole == joined
    parts = sum(
        f["bytes"] for n in "abc" for f in open_dataset(tmp_path / n).manifest["files"].values()
    )
    assert sum(seen) == parts
    ds = open_dataset(tmp_path / "joined", verify=True)
    np.testing.assert_array_equal(ds.segment(4).action, segs[4].action)


def test_appending_a_damaged_or_foreign_dataset_fails_and_writes_nothing(tmp_path):
    segs = list(random_episodes(ATARI, 3, 5, seed=3))
    with DatasetWriter(tmp_path / "part", ATARI) as w:
        w.extend(segs)
    with DatasetWriter(tmp_path / "other", CARTPOLE) as w:
        w.extend(random_episodes(CARTPOLE, 1, 5, seed=0))
    with pytest.raises(SpecError, match="schema differs"):
        with DatasetWriter(tmp_path / "out", ATARI) as w:
            w.append_dataset(tmp_path / "other")
    column = tmp_path / "part" / "steps" / "observation.zlib"
    data = bytearray(column.read_bytes())
    data[-1] ^= 0xFF
    column.write_bytes(bytes(data))
    with pytest.raises(RluError, match="differ from the sha256"):
        with DatasetWriter(tmp_path / "out", ATARI) as w:
            w.append_dataset(tmp_path / "part")
    assert not (tmp_path / "out").exists()


def test_zlib_images_are_smaller_than_raw(tmp_path):
    frames = np.zeros((201, 84, 84), np.uint8)
    frames[:, 40:44, 10:70] = 200  # mostly flat frames, like Atari screens
    ep = make_episode(frames, np.zeros(200, np.int64), np.zeros(200), terminal=True)
    sizes = {}
    for enc in ("raw", "zlib"):
        schema = Schema.for_task(get_task("atari/Pong"), image_encoding=enc)
        with DatasetWriter(tmp_path / enc, schema) as w:
            w.append(ep)
        files = open_dataset(tmp_path / enc).manifest["files"]
        sizes[enc] = sum(v["bytes"] for k, v in files.items() if "observation" in k)
    assert sizes["zlib"] * 10 < sizes["raw"]


def test_threaded_zlib_writes_the_bytes_of_one_frame_at_a_time(tmp_path, monkeypatch):
    from rlu.data.store import writer

    rng = np.random.default_rng(3)
    frames = np.zeros((301, 84, 84), np.uint8)
    frames[:, 30:50] = rng.integers(0, 255, (301, 20, 84), np.uint8)
    ep = make_episode(frames, np.zeros(300, np.int64), np.zeros(300), terminal=True)
    schema = Schema.for_task(get_task("atari/Pong"), image_encoding="zlib")
    manifests = {}
    for name, threshold in (("threaded", 2), ("serial", 10**9)):
        monkeypatch.setattr(writer, "_ZLIB_THREADED_FRAMES", threshold)
        with DatasetWriter(tmp_path / name, schema) as w:
            w.append(ep)
        manifests[name] = open_dataset(tmp_path / name, verify=True).manifest["files"]
    assert manifests["threaded"] == manifests["serial"]  # same sha256 for every file
    stored = open_dataset(tmp_path / "threaded").segment(0).observation
    np.testing.assert_array_equal(stored, frames)


CHILD = r"""
import sys
from rlu.data import DatasetWriter, Schema
from rlu.data.synthetic import random_episodes
from rlu.tasks import get_task
schema = Schema.for_task(get_task("atari/Pong"), image_encoding="zlib")
w = DatasetWriter(sys.argv[1], schema, {"source": "crash-test", "seed": 7})
for i, seg in enumerate(random_episodes(schema, 12, 30, seed=7)):
    w.append(seg)
    print(i, flush=True)
    if i == int(sys.argv[2]):
        sys.stdin.readline()  # hold here, mid-write, until killed
w.close()
print("closed", flush=True)
"""


def _run_child(dest: Path, stop_at: int, kill: bool) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(dest), str(stop_at)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=Path(__file__).resolve().parents[2],
    )
    for line in proc.stdout:
        if line.strip() == str(stop_at):
            break
    if kill:
        os.kill(proc.pid, signal.SIGKILL)
    else:
        proc.stdin.write("\n")
        proc.stdin.flush()
    proc.wait(timeout=120)
    if not kill:
        assert proc.returncode == 0


def _tree_bytes(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def test_sigkill_mid_write_leaves_nothing_loadable_and_rerun_is_byte_identical(tmp_path):
    dest = tmp_path / "crashed"
    _run_child(dest, stop_at=5, kill=True)
    assert not dest.exists()
    with pytest.raises(FormatError, match="not a complete rlu dataset"):
        open_dataset(dest)
    assert (tmp_path / ".crashed.partial").exists()  # only the hidden partial directory remains
    # rerun into the same place with the same seed, and an uninterrupted run elsewhere
    _run_child(dest, stop_at=0, kill=False)
    _run_child(tmp_path / "clean", stop_at=0, kill=False)
    assert not (tmp_path / ".crashed.partial").exists()
    assert _tree_bytes(dest) == _tree_bytes(tmp_path / "clean")
    assert len(open_dataset(dest, verify=True)) == 12


def test_exception_inside_writer_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with DatasetWriter(tmp_path / "ds", CARTPOLE) as w:
            w.append(next(random_episodes(CARTPOLE, 1, 3)))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_shape_mismatch_names_the_key_and_writes_nothing(tmp_path):
    good, bad = list(random_episodes(CARTPOLE, 2, 4, seed=0))
    bad.observation["velocity"] = np.zeros((5, 3), np.float32)
    with DatasetWriter(tmp_path / "ds", CARTPOLE) as w:
        w.append(good)
        with pytest.raises(SpecError, match="observation/velocity"):
            w.append(bad)
    ds = open_dataset(tmp_path / "ds", verify=True)
    assert len(ds) == 1 and ds.num_steps == 5


def test_missing_key_and_wrong_dtype_are_named(tmp_path):
    seg = next(random_episodes(CARTPOLE, 1, 4))
    del seg.observation["position"]
    with DatasetWriter(tmp_path / "a", CARTPOLE) as w, pytest.raises(SpecError, match="position"):
        w.append(seg)
    seg = next(random_episodes(CARTPOLE, 1, 4))
    seg.observation["position"] = seg.observation["position"].astype(np.complex64)
    with DatasetWriter(tmp_path / "b", CARTPOLE) as w, pytest.raises(SpecError, match="dtype"):
        w.append(seg)


def test_existing_destination_is_refused(tmp_path):
    write_synthetic(tmp_path / "ds", CARTPOLE, 1, 3)
    with pytest.raises(RluError, match="already exists"):
        DatasetWriter(tmp_path / "ds", CARTPOLE)


def test_corrupt_manifest_is_named(tmp_path):
    path = write_synthetic(tmp_path / "ds", CARTPOLE, 2, 3)
    (path / "manifest.json").write_text("{not json")
    with pytest.raises(FormatError, match=r"manifest\.json.*corrupt JSON"):
        open_dataset(path)
    (path / "manifest.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(FormatError, match="'format'"):
        open_dataset(path)


def test_missing_file_is_named(tmp_path):
    path = write_synthetic(tmp_path / "ds", CARTPOLE, 2, 3)
    (path / "steps" / "reward.bin").unlink()
    with pytest.raises(FormatError, match=r"reward\.bin.*missing"):
        open_dataset(path)


def test_checksum_mismatch_is_named(tmp_path):
    path = write_synthetic(tmp_path / "ds", CARTPOLE, 2, 3)
    f = path / "steps" / "observation" / "position.bin"
    data = bytearray(f.read_bytes())
    data[5] ^= 0xFF
    f.write_bytes(bytes(data))
    open_dataset(path)  # sizes agree: opening without verify succeeds
    with pytest.raises(FormatError, match=r"position\.bin: sha256"):
        open_dataset(path, verify=True)


def test_truncated_column_is_named(tmp_path):
    path = write_synthetic(tmp_path / "ds", CARTPOLE, 2, 3)
    f = path / "steps" / "action.bin"
    f.write_bytes(f.read_bytes()[:-4])
    with pytest.raises(FormatError, match=r"action\.bin"):
        open_dataset(path)
