"""Conversion into the store: every registered family, atomic failure, batched appends, CLI."""

from __future__ import annotations

import gzip
import json
import shutil

import numpy as np
import pytest

from rlu.cli import main
from rlu.data.release import families as Fm
from rlu.data.release.convert import _fit, append_batch, convert, schema_for
from rlu.data.store import DatasetWriter, open_dataset
from rlu.data.validate import validate
from rlu.tasks import get_task
from rlu.types import RluError
from tests.release.test_families import atari_episode, atari_record, rwrl_record


def _window(rng, task, t, step_type, discount=None, extra=True):
    rec = {}
    for k, spec in task.observation_spec.items():
        if spec.dtype == "uint8":
            rec[f"observation/{k}"] = rng.integers(0, 256, (t, *spec.shape), dtype=np.uint8)
        else:
            rec[f"observation/{k}"] = rng.standard_normal((t, *spec.shape)).astype(np.float32)
    if extra:  # files hold keys no loader names (docs/release_format.md §3.3)
        rec["observation/walker/sensors_torque"] = np.zeros((t, 6), np.float32)
    rec["action"] = rng.uniform(-1, 1, (t, task.action_dim)).astype(np.float32)
    rec["reward"] = rng.random(t).astype(np.float32)
    rec["discount"] = np.ones(t, np.float32) if discount is None else np.float32(discount)
    rec["step_type"] = np.float32(step_type)
    return rec


def _windows(task_id, n=20, t=2, seed=0):
    rng = np.random.default_rng(seed)
    task = get_task(task_id)
    kinds = [[0] + [1] * (t - 1), [1] * t, [1] * (t - 1) + [2]]
    return [_window(rng, task, t, kinds[i % 3]) for i in range(n)]


def _shard(tmp_path, family, recs, name="train-00000-of-00001"):
    path = tmp_path / family / name
    path.parent.mkdir(parents=True, exist_ok=True)
    Fm.write_shard(path, family, recs)
    return path


CASES = [
    (
        "dm_control_suite",
        "control_suite/walker_walk",
        lambda: _windows("control_suite/walker_walk"),
    ),
    (
        "dm_locomotion",
        "locomotion/humanoid_corridor",
        lambda: _windows("locomotion/humanoid_corridor", n=6),
    ),
    (
        "dm_locomotion",
        "locomotion/humanoid_walls",
        lambda: _windows("locomotion/humanoid_walls", n=3, t=40),
    ),
    (
        "atari",
        "atari/Pong",
        lambda: [atari_record(np.random.default_rng(i), float(i % 4 > 0)) for i in range(6)],
    ),
    (
        "atari_episodes_ordered",
        "atari/Pong",
        lambda: [
            atari_episode(np.random.default_rng(1), 7),
            atari_episode(np.random.default_rng(2), 5, 1.0),
        ],
    ),
]


@pytest.mark.parametrize("family,task,make", CASES)
def test_convert_family_and_validate(tmp_path, family, task, make):
    recs = make()
    path = _shard(tmp_path, family, recs)
    out = tmp_path / "ds"
    rep = convert([path], family, task, out, workers=1)
    ds = open_dataset(out, verify=True)
    assert rep.records == len(recs) and len(ds) == len(recs)
    report = validate(out)
    assert report.ok, report.problems
    assert ds.schema.task_id == task
    if family == "atari_episodes_ordered":
        assert ds.schema.frame_stack == 4 and ds.manifest["counts"]["episodes"] == 2
        s = ds.segment(0)
        assert np.array_equal(s.observation, recs[0]["observations"])


def test_convert_episode_files(tmp_path):
    rng = np.random.default_rng(3)
    task = get_task("control_suite/cartpole_swingup")
    recs = []
    for t, last in ((6, 1.0), (4, 0.0)):
        r = _window(rng, task, t, [0] + [1] * (t - 2) + [2], extra=False)
        r["discount"][-1] = last
        r["episode_id"] = np.int64(t)
        recs.append(r)
    path = _shard(tmp_path, "dm_control_suite_episodes", recs)
    out = tmp_path / "ds"
    convert([path], "dm_control_suite_episodes", task.id, out, workers=1)
    ds = open_dataset(out)
    assert ds.manifest["counts"]["episodes"] == 2 and validate(out).ok
    assert ds.segment(1).is_terminal[-1] and not ds.segment(0).is_terminal.any()


def test_convert_rwrl_easy(tmp_path):
    rng = np.random.default_rng(4)
    task = get_task("rwrl/cartpole_swingup")
    recs = [rwrl_record(rng, 21, easy=True) for _ in range(3)]
    path = _shard(tmp_path, "rwrl", recs, "episodes.tfrecord-00000-of-00001")
    out = tmp_path / "ds"
    with pytest.raises(RluError, match="--challenge"):
        convert([path], "rwrl", task.id, out)
    convert([path], "rwrl", task.id, out, challenge="easy", workers=1)
    ds = open_dataset(out)
    assert ds.manifest["counts"]["episodes"] == 3 and "observation/dummy-9" in ds.observation_keys()
    assert validate(out).ok


def test_batched_append_writes_the_same_bytes(tmp_path):
    path = _shard(tmp_path, "dm_control_suite", _windows("control_suite/walker_walk", n=30))
    task = get_task("control_suite/walker_walk")
    schema = schema_for(task, "dm_control_suite")
    batches = [_fit(b, schema, "x") for b in Fm.iter_segments(path, "dm_control_suite")]
    with DatasetWriter(tmp_path / "a", schema) as w:
        for b in batches:
            append_batch(w, b)
    with DatasetWriter(tmp_path / "b", schema) as w:
        for b in batches:
            for s in b:
                w.append(s)
    ma = json.loads((tmp_path / "a" / "manifest.json").read_text())
    mb = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert ma == mb


@pytest.mark.parametrize("family,task,make", CASES[::2], ids=lambda v: str(v)[:24])
def test_decode_batches_bounded_in_bytes_write_the_same_bytes(
    tmp_path, family, task, make, monkeypatch
):
    """Records are decoded in batches of at most ``_BATCH_BYTES`` (so long records never pile
    up); where the batches end changes nothing in the dataset."""
    path = _shard(tmp_path, family, make())
    convert([path], family, task, tmp_path / "whole", workers=1)
    monkeypatch.setattr(Fm, "_BATCH_BYTES", 1)  # every record its own batch
    convert([path], family, task, tmp_path / "each", workers=1)
    manifests = [
        json.loads((tmp_path / d / "manifest.json").read_text()) for d in ("whole", "each")
    ]
    whole, each = manifests
    assert whole["files"] == each["files"]


PARALLEL_CASES = [
    (
        "dm_control_suite",
        "control_suite/walker_walk",
        lambda i: _windows("control_suite/walker_walk", 40, seed=i),
    ),
    (  # image columns deflated by the readers, not the writer
        "atari",
        "atari/Pong",
        lambda i: [
            atari_record(np.random.default_rng(10 * i + j), float(j % 5 > 0)) for j in range(12)
        ],  # fmt: skip
    ),
]


@pytest.mark.parametrize("family,task,make", PARALLEL_CASES, ids=["control", "atari"])
def test_parallel_conversion_is_deterministic(tmp_path, family, task, make):
    paths = [_shard(tmp_path, family, make(i), f"train-{i:05d}-of-00003") for i in range(3)]
    for w in (1, 2, 3):
        convert(paths, family, task, tmp_path / f"o{w}", workers=w)
    files = [
        json.loads((tmp_path / f"o{w}" / "manifest.json").read_text())["files"] for w in (1, 2, 3)
    ]
    assert files[0] == files[1] == files[2]
    assert any(name.endswith(".zlib") for name in files[0]) == (family == "atari")
    ds = open_dataset(tmp_path / "o2", verify=True)
    assert len(ds) == sum(len(make(i)) for i in range(3))


def test_readers_send_image_columns_deflated(tmp_path):
    from rlu.data.release.convert import ShardJob, shard_batches
    from rlu.data.store import Deflated, SegmentColumns

    recs = [atari_record(np.random.default_rng(j), 1.0) for j in range(5)]
    path = _shard(tmp_path, "atari", recs)
    schema = schema_for(get_task("atari/Pong"), "atari")
    job = ShardJob("atari", schema, {"run": 1}, True, "raise")
    out = [b for b, stats in shard_batches(job, str(path), columns=True) if stats is None]
    assert out and all(isinstance(b, SegmentColumns) for b in out)
    assert all(isinstance(b.columns["observation"], Deflated) for b in out)
    assert all(isinstance(b.columns["action"], np.ndarray) for b in out)  # only images deflate
    assert sum(len(b) for b in out) == 5 and all(b.metadata["run"][0] == 1 for b in out)


@pytest.mark.parametrize("workers", [1, 2])
def test_failed_conversion_leaves_nothing(tmp_path, workers):
    good = _shard(
        tmp_path,
        "dm_control_suite",
        _windows("control_suite/walker_walk", 40),
        "train-00000-of-00002",
    )
    bad = _shard(
        tmp_path,
        "dm_control_suite",
        _windows("control_suite/walker_walk", 40, seed=1),
        "train-00001-of-00002",
    )
    raw = bytearray(gzip.decompress(bad.read_bytes()))
    raw[len(raw) // 2] ^= 0xFF
    bad.write_bytes(gzip.compress(bytes(raw)))
    out = tmp_path / "out"
    with pytest.raises(RluError, match="CRC mismatch"):
        convert([good, bad], "dm_control_suite", "control_suite/walker_walk", out, workers=workers)
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    # the CLI: non-zero exit, nothing at --out; --skip-corrupt converts the rest and reports
    code = main(
        [
            "convert",
            "--family",
            "dm_control_suite",
            "--task",
            "control_suite/walker_walk",
            "--out",
            str(out),
            str(good),
            str(bad),
        ]
    )
    assert code != 0 and not out.exists()
    code = main(
        [
            "convert",
            "--family",
            "dm_control_suite",
            "--task",
            "control_suite/walker_walk",
            "--out",
            str(out),
            "--skip-corrupt",
            str(good),
            str(bad),
        ]
    )
    assert code == 0 and len(open_dataset(out)) == 79


def test_wrong_task_for_the_files(tmp_path):
    path = _shard(tmp_path, "dm_control_suite", _windows("control_suite/walker_walk", 5))
    with pytest.raises(RluError, match="not in the file"):
        convert([path], "dm_control_suite", "control_suite/cheetah_run", tmp_path / "x", workers=1)
    with pytest.raises(RluError, match="no release family"):
        convert([path], "atari", "control_suite/cheetah_run", tmp_path / "x")
    with pytest.raises(RluError, match="no release family 'bsuite'"):  # bsuite's tasks' own
        convert([path], "bsuite", "control_suite/cheetah_run", tmp_path / "x")
    with pytest.raises(RluError, match="no release family 'dmlab'"):  # DMLab's tasks' own
        convert([path], "dmlab", "control_suite/cheetah_run", tmp_path / "x")
    assert not (tmp_path / "x").exists()


def test_cli_convert_src_root(tmp_path, capsys):
    root = tmp_path / "bucket"
    d = root / "dm_control_suite" / "walker_walk"
    d.mkdir(parents=True)
    for i in range(2):
        Fm.write_shard(
            d / f"train-{i:05d}-of-00002",
            "dm_control_suite",
            _windows("control_suite/walker_walk", 10, seed=i),
        )
    out = tmp_path / "ds"
    args = ["convert", "--family", "dm_control_suite", "--task", "control_suite/walker_walk"]
    code = main([*args, "--out", str(out), "--src", str(root)])
    assert code == 0 and len(open_dataset(out)) == 20
    assert "20 segments" in capsys.readouterr().out
    shutil.rmtree(out)
    code = main([*args, "--out", str(out), "--src", str(root), "--shards", "1"])
    assert code == 0 and len(open_dataset(out)) == 10
    (d / "train-00001-of-00002").unlink()
    code = main([*args, "--out", str(tmp_path / "y"), "--src", str(root)])
    assert code == 2 and "missing" in capsys.readouterr().err
