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
