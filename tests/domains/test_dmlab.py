"""DeepMind Lab as a domain: its tasks in ``rlu list`` as data only, a TensorFlow-written shard
(scripts/fixtures/write_dmlab_shard.py) converted from the command line into exactly the arrays
TensorFlow was given (frames back in RGB), a damaged shard refused with the file named, and the
env refused with what is missing (no traceback)."""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import numpy as np
import pytest

from rlu.cli import main
from rlu.types import RluError

TASK = "dmlab/seekavoid_arena_01"
SHARD = Path(__file__).resolve().parents[1] / "fixtures" / "release" / "dmlab"
SHARD = SHARD / "seekavoid_arena_01" / "training_0" / "tfrecord-00000-of-00500"


def test_dmlab_tasks_are_listed_as_data_only(capsys):
    assert main(["list", "--domain", "dmlab"]) == 0
    out = capsys.readouterr().out
    for level in ("seekavoid_arena_01", "explore_object_rewards_few", "rooms_watermaze"):
        assert f"dmlab/{level}" in out
    assert "5 tasks" in out
    assert "dmlab: data only, no env (DeepMind Lab is data only here: deepmind_lab is not" in out
    assert main(["list", "--domain", "bsuite"]) == 0
    assert "data only" not in capsys.readouterr().out  # bsuite has an env
    assert main(["info", TASK]) == 0
    assert 'data_only: "no env: DeepMind Lab is data only here' in capsys.readouterr().out


def test_making_the_env_refuses_with_what_is_missing():
    import rlu

    with pytest.raises(RluError) as e:
        rlu.make_env(TASK)
    msg = str(e.value)
    assert msg.startswith(f"{TASK}: DeepMind Lab is data only here")
    assert "rlu convert FILE --family dmlab" in msg and "--eval-every -1" in msg
    if e.value.__class__ is RluError and "not installed" in msg:  # without deepmind_lab
        assert "bazel build" in msg


def _convert(tmp_path: Path, shard: Path = SHARD) -> Path:
    out = tmp_path / "data"
    argv = ["convert", str(shard), "--family", "dmlab", "--task", TASK, "--out", str(out)]
    assert main(argv) == 0
    return out


def test_a_tf_written_dmlab_shard_converts_to_its_arrays(tmp_path):
    from rlu.data.store import open_dataset

    ds = open_dataset(_convert(tmp_path))
    exp = np.load(f"{SHARD}.npz")
    n, t = exp["actions"].shape
    assert ds.schema.task_id == TASK and ds.num_segments == n == 3 and ds.num_steps == n * t
    assert sorted(ds.schema.observation) == ["last_action", "last_reward", "pixels"]
    assert ds.manifest["provenance"]["run"] == "training_0"  # the shard's run folder
    for i in range(n):
        s = ds.segment(i)
        pixels = np.asarray(s.observation["pixels"])
        assert pixels.dtype == np.uint8 and pixels.shape == (t, 72, 96, 3)
        assert np.array_equal(pixels, exp["rgb"][i])  # RGB: the stored BGR reversed
        assert np.array_equal(pixels, exp["observations_pixels"][i][..., ::-1])
        assert np.array_equal(s.observation["last_action"], exp["observations_action"][i])
        assert np.array_equal(s.observation["last_reward"], exp["observations_reward"][i])
        assert np.array_equal(s.action, exp["actions"][i])
        assert np.array_equal(s.reward, exp["rewards"][i])
        assert np.array_equal(s.discount, exp["discounts"][i])
        assert s.is_first.tolist() == [True] + [False] * (t - 1)
        assert s.is_last.tolist() == [False] * (t - 1) + [True]
        assert not s.is_terminal.any()  # discount 1 throughout: the level's time limit ends it
        assert s.metadata["episode_id"] == exp["episode_id"][i]
        assert s.metadata["episode_return"] == exp["episode_return"][i]
    # the last action one-hot is the previous step's action
    s = ds.segment(0)
    assert np.array_equal(np.asarray(s.observation["last_action"])[1:].argmax(-1), s.action[:-1])


def test_the_release_reader_returns_the_stored_arrays():
    from rlu.data.release import families as Fm

    exp = np.load(f"{SHARD}.npz")
    raw = Fm.read_raw(SHARD, "dmlab")
    for k in exp.files:
        if k == "rgb":
            continue
        got = np.asarray(raw[k]).astype(exp[k].dtype)
        assert got.shape == exp[k].shape and got.tobytes() == exp[k].tobytes(), k
    segments = [s for b in Fm.iter_segments(SHARD, "dmlab") for s in b]
    assert len(segments) == 3
    for s, rgb in zip(segments, exp["rgb"], strict=True):
        assert np.array_equal(s.observation["pixels"], rgb)


def _damaged(tmp_path: Path, how: str) -> Path:
    path = tmp_path / "dmlab" / "seekavoid_arena_01" / "training_0" / SHARD.name
    path.parent.mkdir(parents=True)
    body = SHARD.read_bytes()
    if how == "truncated":
        path.write_bytes(body[:5000])
    else:  # one payload byte flipped, the gzip stream itself intact
        plain = bytearray(gzip.decompress(body))
        plain[3000] ^= 0xFF
        path.write_bytes(gzip.compress(bytes(plain)))
    return path


@pytest.mark.parametrize(
    "how,why", [("truncated", "truncated record"), ("flipped", "payload CRC mismatch")]
)
def test_a_damaged_shard_is_refused_naming_the_file(tmp_path, capsys, how, why):
    from rlu.data.release.convert import convert

    path = _damaged(tmp_path, how)
    out = tmp_path / "out"
    argv = ["convert", str(path), "--family", "dmlab", "--task", TASK, "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"rlu: error: {path}: {why}" in err and "download it again" in err
    assert "Traceback" not in err and not out.exists()
    with pytest.raises(RluError, match=why):
        convert([str(path)], "dmlab", TASK, tmp_path / "out2")


def test_a_record_of_the_wrong_frame_size_is_refused(tmp_path):
    from rlu.data.release import families as Fm
    from rlu.data.release.convert import convert

    raw = {k: v[0] for k, v in np.load(f"{SHARD}.npz").items() if k != "rgb"}
    raw["observations_pixels"] = np.ascontiguousarray(raw["observations_pixels"][:, :64])
    path = tmp_path / "training_0" / SHARD.name
    path.parent.mkdir()
    Fm.write_shard(path, "dmlab", [raw])
    with pytest.raises(RluError, match=r"observations_pixels.*72"):
        convert([str(path)], "dmlab", TASK, tmp_path / "out")
    shutil.rmtree(tmp_path / "out", ignore_errors=True)
