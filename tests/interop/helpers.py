"""Shared checks for the interop tests: transitions and segments of two datasets are equal."""

from __future__ import annotations

import numpy as np

from rlu.data import TransitionView


def all_transitions(ds):
    view = TransitionView(ds)
    return view.batch(np.arange(len(view)))


def assert_same_transitions(a, b):
    x, y = all_transitions(a), all_transitions(b)
    for field in x._fields:
        u, v = getattr(x, field), getattr(y, field)
        if isinstance(u, dict):
            assert set(u) == set(v), field
            for k in u:
                np.testing.assert_array_equal(u[k], v[k], err_msg=f"{field}/{k}")
        else:
            np.testing.assert_array_equal(u, v, err_msg=field)


def assert_same_segments(
    a, b, fields=("action", "reward", "discount", "is_first", "is_last", "is_terminal")
):
    assert len(a) == len(b)
    for i in range(len(a)):
        s, t = a.segment(i), b.segment(i)
        if isinstance(s.observation, dict):
            assert set(s.observation) == set(t.observation)
            for k in s.observation:
                np.testing.assert_array_equal(s.observation[k], t.observation[k], err_msg=k)
        else:
            np.testing.assert_array_equal(s.observation, t.observation)
        if s.frame_prefix is not None or t.frame_prefix is not None:
            np.testing.assert_array_equal(s.frame_prefix, t.frame_prefix)
        for f in fields:
            np.testing.assert_array_equal(getattr(s, f), getattr(t, f), err_msg=f"segment {i} {f}")


def _column(ds, name):
    col = ds.column(name)
    return col[:] if hasattr(col, "take") else np.asarray(col)


def assert_same_dataset(a, b) -> dict[str, int]:
    """Two stored datasets are the same: schema, counts and provenance in the manifest, every
    step (and frame) column row by row with its dtype (every episode's last row included), the
    segment index, every metadata column (missing values included), the episode returns, and
    every attached file byte for byte. Returns what was compared."""
    from rlu.data.roundtrip import attachments
    from rlu.segments import METADATA_FIELDS

    for key in ("schema", "counts", "provenance"):
        assert a.manifest[key] == b.manifest[key], key
    n = {"columns": 0, "rows": 0, "segments": len(a), "metadata": 0, "attachments": 0}
    names = [*a.schema.step_columns(), *a.schema.frame_columns()]
    for name in names:
        x, y = _column(a, name), _column(b, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)
        n["columns"] += 1
        n["rows"] += len(x)
    for name in ("start", "length", "frame_start"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for key in METADATA_FIELDS:
        np.testing.assert_array_equal(a.metadata(key), b.metadata(key), err_msg=key)
        n["metadata"] += 1
    np.testing.assert_array_equal(a.episode_returns(), b.episode_returns())
    assert attachments(a) == attachments(b)
    for rel in attachments(a):
        assert a.file(rel).read_bytes() == b.file(rel).read_bytes(), rel
        n["attachments"] += 1
    return n
