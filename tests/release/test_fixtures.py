"""Shards written by TensorFlow itself: our reader returns the original loaders' arrays bit for bit,
and the converted dataset's D4RL export is exactly the loader's SARSA tuples."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rlu.data.d4rl import to_d4rl
from rlu.data.release import families as Fm
from rlu.data.release.convert import convert
from rlu.data.release.framing import RecordReader
from rlu.data.store import open_dataset
from rlu.data.validate import validate
from rlu.types import SpecError

SHARDS = [
    ("dm_control_suite/cartpole_swingup/train-00000-of-00001", "dm_control_suite",
     "control_suite/cartpole_swingup"),
    ("atari/Pong/run_1-00000-of-00001", "atari", "atari/Pong"),
]  # fmt: skip


def _bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("shard,family,task", SHARDS)
def test_framing_matches_tf_offsets(fixtures, shard, family, task):
    meta = json.loads((fixtures / "expected" / f"{shard}.json").read_text())
    r = RecordReader(fixtures / "data" / shard)
    lengths = [len(p) for p in r]
    assert lengths == [rec["length"] for rec in meta["records"]]
    assert r.stats.compressed and r.stats.bytes_read == meta["uncompressed_stream_bytes"]


@pytest.mark.parametrize("shard,family,task", SHARDS)
def test_loader_arrays_bit_for_bit(fixtures, shard, family, task):
    raw = Fm.read_raw(fixtures / "data" / shard, family)
    exp = np.load(fixtures / "expected" / f"{shard}.npz")
    keys = [k for k in exp.files if not k.startswith("sarsa/") and k != "raw_episode_id_int64"]
    assert keys
    for k in keys:
        assert _bits(raw[k], exp[k]), k
    if "raw_episode_id_int64" in exp.files:
        assert _bits(raw["episode_id"].view(np.int64), exp["raw_episode_id_int64"])


@pytest.mark.parametrize("workers", [1, 2])
def test_control_windows_convert_to_loader_tuples(fixtures, tmp_path, workers):
    shard = SHARDS[0][0]
    out = tmp_path / "ds"
    convert([fixtures / "data" / shard], "dm_control_suite", "control_suite/cartpole_swingup",
            out, workers=workers)  # fmt: skip
    d = to_d4rl(open_dataset(out))
    exp = np.load(fixtures / "expected" / f"{shard}.npz")
    n = exp["sarsa/r_t"].shape[0]
    assert d["rewards"].shape == (n,)  # one transition per 2-step window
    assert _bits(d["rewards"], exp["sarsa/r_t"])
    assert _bits(d["actions"], exp["sarsa/a_tm1"])
    for key in ("position", "velocity"):
        assert _bits(d[f"observations/{key}"], exp[f"sarsa/o_tm1/{key}"])
        assert _bits(d[f"next_observations/{key}"], exp[f"sarsa/o_t/{key}"])
    # discount p_t: D4RL keeps it as terminals = (p_t == 0)
    assert np.array_equal(d["terminals"], exp["sarsa/p_t"] == 0)
    ds = open_dataset(out)
    from rlu.data.views import TransitionView

    t = TransitionView(ds).all()
    assert _bits(t.discount, exp["sarsa/p_t"]) and _bits(t.next_action, exp["sarsa/a_t"])
    assert validate(out).ok


def test_atari_converts_to_loader_tuples(fixtures, tmp_path):
    # the fixture's actions are random in [0, 18) (README: "random but fixed contents"); Pong's
    # minimal action set has 6, so as Pong the shard is refused at the first action >= 6, and it
    # is converted as a game of 18 actions
    shard = SHARDS[1][0]
    exp = np.load(fixtures / "expected" / f"{shard}.npz")
    first = int(np.flatnonzero(exp["a_t"] >= 6)[0])
    with pytest.raises(SpecError, match=rf"action {exp['a_t'][first]} \(segment {first}, step 0\)"):
        convert([fixtures / "data" / shard], "atari", "atari/Pong", tmp_path / "pong", workers=2)
    assert not (tmp_path / "pong").exists()
    out = tmp_path / "ds"
    convert([fixtures / "data" / shard], "atari", "atari/Zaxxon", out, workers=2)
    ds = open_dataset(out)
    from rlu.data.views import TransitionView

    t = TransitionView(ds).all()
    assert _bits(t.observation, exp["o_t"]) and _bits(t.next_observation, exp["o_tp1"])
    assert np.array_equal(t.action, exp["a_t"]) and np.array_equal(t.next_action, exp["a_tp1"])
    assert _bits(t.reward, exp["r_t"]) and _bits(t.discount, exp["d_t"])
    assert _bits(ds.metadata("episode_id"), exp["episode_id"])
    # the transitions' return is summed from clipped rewards: it is the clipped return, and the
    # raw game score is unknown in this family
    clipped = exp["episode_return"].astype(np.float64)
    assert np.array_equal(ds.metadata("clipped_episode_return"), clipped)
    assert np.isnan(ds.metadata("episode_return")).all()
    assert np.all(ds.metadata("run") == 1)
    assert validate(out).ok
