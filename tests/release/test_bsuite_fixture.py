"""A bsuite shard TensorFlow wrote (scripts/fixtures/write_bsuite_shard.py): the reader returns
its arrays bit for bit, and the segments follow the bsuite rule (every LAST is terminal)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rlu.data.release import families as Fm

SHARD = Path(__file__).resolve().parents[1] / "fixtures" / "release" / "bsuite" / "catch"
SHARD = SHARD / "0_0.1" / "0_full-00000-of-00001"


def test_tf_written_bsuite_shard_reads_bit_for_bit():
    raw = Fm.read_raw(SHARD, "bsuite")
    exp = np.load(f"{SHARD}.npz")
    assert sorted(raw) == sorted(exp.files)
    for k in exp.files:
        got = raw[k].astype(exp[k].dtype)
        assert got.shape == exp[k].shape and got.tobytes() == exp[k].tobytes(), k


def test_tf_written_bsuite_shard_segments():
    segments = [s for b in Fm.iter_segments(SHARD, "bsuite") for s in b]
    exp = np.load(f"{SHARD}.npz")
    assert len(segments) == len(exp["step_type"]) == 9
    last = exp["step_type"][:, 1] == 2
    assert [bool(s.is_terminal[1]) for s in segments] == last.tolist()
    assert [float(s.discount[0]) for s in segments] == (~last).astype(float).tolist()
