"""Every view equals a slow, obviously-correct reference built step by step from the segments."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rlu.data import DatasetWriter, Schema, Segment, SequenceView, TransitionView, open_dataset
from rlu.types import ArraySpec, BoundedSpec, DiscreteSpec

DICT_SCHEMA = Schema(
    {"a": ArraySpec((2,), "float32"), "cam": ArraySpec((3, 3, 2), "uint8")},
    BoundedSpec((1,), "float32"),
)
FRAME_SCHEMA = Schema(ArraySpec((3, 2), "uint8"), DiscreteSpec((), "int64", 4), frame_stack=4)


@st.composite
def segments(draw, frames: bool):
    """Random segments: whole episodes (terminal or truncated), length-1 episodes, bare windows."""
    n_seg = draw(st.integers(1, 5))
    seed = draw(st.integers(0, 2**31))
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_seg):
        n = draw(st.sampled_from([1, 2, 2, 3, 5, 8]))
        kind = draw(st.sampled_from(["terminal", "truncated", "window", "window_end"]))
        first = np.zeros(n, bool)
        last = np.zeros(n, bool)
        term = np.zeros(n, bool)
        disc = np.ones(n, np.float32)
        if kind in ("terminal", "truncated"):
            first[0], last[-1] = True, True
            disc[-1] = 0.0
            if kind == "terminal":
                term[-1] = True
                if n >= 2:
                    disc[-2] = 0.0
        elif kind == "window_end":  # a release window that reaches its episode's terminal end
            last[-1], term[-1] = True, True
            disc[-1] = 0.0
            if n >= 2:
                disc[-2] = 0.0
        reward = rng.standard_normal(n).astype(np.float32)
        if frames:
            obs = rng.integers(0, 256, (n, 3, 2), dtype=np.uint8)
            action = rng.integers(0, 4, n).astype(np.int64)
            prefix = None if first[0] else rng.integers(0, 256, (3, 3, 2), dtype=np.uint8)
        else:
            obs = {
                "a": rng.standard_normal((n, 2)).astype(np.float32),
                "cam": rng.integers(0, 256, (n, 3, 3, 2), dtype=np.uint8),
            }
            action = rng.uniform(-1, 1, (n, 1)).astype(np.float32)
            prefix = None
        out.append(Segment(obs, action, reward, disc, first, last, term, {}, prefix))
    return out


def write(tmp_path, segs, schema, encoding="raw"):
    import dataclasses

    schema = dataclasses.replace(schema, image_encoding=encoding)
    path = tmp_path / f"ds_{np.random.default_rng().integers(1 << 60)}"
    with DatasetWriter(path, schema) as w:
        for s in segs:
            w.append(s)
    return open_dataset(path, verify=True)


def obs_at(seg: Segment, t: int, stack: int):
    """Reference observation of step t: the stored one, or the last ``stack`` frames."""
    if stack == 1:
        if isinstance(seg.observation, dict):
            return {k: v[t] for k, v in seg.observation.items()}
        return seg.observation[t]
    prefix = seg.frame_prefix
    if prefix is None:
        prefix = np.zeros((stack - 1, *seg.observation.shape[1:]), np.uint8)
    frames = np.concatenate([prefix, seg.observation])
    return np.stack([frames[t + j] for j in range(stack)], axis=-1)


def ref_transitions(segs, stack, n_step=1, gamma=1.0, clip=None):
    rows = []
    for seg in segs:
        T = len(seg)
        for t in range(T - 1):
            if n_step > 1 and t + n_step > T - 1 and not seg.is_terminal[-1]:
                continue  # window would cross a truncated end: left out
            ret, disc, k = 0.0, 1.0, 0
            for i in range(n_step):
                if t + i >= T - 1:
                    disc = 0.0  # past a terminal end
                    break
                r = float(seg.reward[t + i])
                r = r if clip is None else min(max(r, -clip), clip)
                ret += (gamma**i) * disc * r
                disc *= float(seg.discount[t + i])
                k = i + 1
            nxt = min(t + n_step, T - 1) if n_step > 1 else t + 1
            if n_step == 1:
                ret, disc = float(seg.reward[t]), float(seg.discount[t])
                ret = ret if clip is None else min(max(ret, -clip), clip)
            rows.append(
                (
                    obs_at(seg, t, stack),
                    seg.action[t],
                    ret,
                    disc,
                    obs_at(seg, nxt, stack),
                    seg.action[nxt],
                )
            )
            del k
    return rows


def assert_obs_equal(got, want):
    if isinstance(want, dict):
        assert set(got) == set(want)
        for k in want:
            np.testing.assert_array_equal(got[k], want[k])
    else:
        np.testing.assert_array_equal(got, want)


def pick(obs, i):
    return {k: v[i] for k, v in obs.items()} if isinstance(obs, dict) else obs[i]


FAST = settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@FAST
@given(segs=segments(frames=False), encoding=st.sampled_from(["raw", "zlib"]))
def test_transitions_equal_reference(tmp_path, segs, encoding):
    ds = write(tmp_path, segs, DICT_SCHEMA, encoding)
    view = TransitionView(ds)
    ref = ref_transitions(segs, 1)
    assert len(view) == len(ref) == sum(len(s) - 1 for s in segs)
    if not ref:
        return
    b = view.all()
    for i, (o, a, r, d, o2, a2) in enumerate(ref):
        assert_obs_equal(pick(b.observation, i), o)
        np.testing.assert_array_equal(b.action[i], a)
        assert b.reward[i] == np.float32(r) and b.discount[i] == np.float32(d)
        assert_obs_equal(pick(b.next_observation, i), o2)
        np.testing.assert_array_equal(b.next_action[i], a2)


@FAST
@given(
    segs=segments(frames=False),
    n_step=st.integers(2, 4),
    gamma=st.sampled_from([1.0, 0.9]),
)
def test_nstep_equal_reference(tmp_path, segs, n_step, gamma):
    ds = write(tmp_path, segs, DICT_SCHEMA)
    view = TransitionView(ds, n_step=n_step, gamma=gamma)
    ref = ref_transitions(segs, 1, n_step, gamma)
    assert len(view) == len(ref)
    if not ref:
        return
    b = view.all()
    for i, (o, a, r, d, o2, a2) in enumerate(ref):
        assert_obs_equal(pick(b.observation, i), o)
        np.testing.assert_array_equal(b.action[i], a)
        np.testing.assert_allclose(b.reward[i], r, rtol=1e-5, atol=1e-6)
        assert b.discount[i] == np.float32(d)
        assert_obs_equal(pick(b.next_observation, i), o2)
        np.testing.assert_array_equal(b.next_action[i], a2)


@FAST
@given(segs=segments(frames=True), encoding=st.sampled_from(["raw", "zlib"]))
def test_frame_stacks_equal_reference(tmp_path, segs, encoding):
    ds = write(tmp_path, segs, FRAME_SCHEMA, encoding)
    view = TransitionView(ds)
    ref = ref_transitions(segs, 4)
    assert len(view) == len(ref)
    if not ref:
        return
    b = view.all()
    assert b.observation.shape[1:] == (3, 2, 4)
    for i, (o, a, r, d, o2, a2) in enumerate(ref):
        np.testing.assert_array_equal(b.observation[i], o)
        np.testing.assert_array_equal(b.next_observation[i], o2)
        assert b.action[i] == a and b.next_action[i] == a2
        assert b.reward[i] == np.float32(r) and b.discount[i] == np.float32(d)


@FAST
@given(
    segs=segments(frames=True),
    n_step=st.integers(1, 4),
    clip=st.sampled_from([None, 0.5]),
    encoding=st.sampled_from(["raw", "zlib"]),
)
def test_nstep_frame_stacks_and_reward_clip_equal_reference(tmp_path, segs, n_step, clip, encoding):
    ds = write(tmp_path, segs, FRAME_SCHEMA, encoding)
    view = TransitionView(ds, n_step=n_step, gamma=0.9, reward_clip=clip)
    ref = ref_transitions(segs, 4, n_step, 0.9, clip)
    assert len(view) == len(ref)
    if not ref:
        return
    b = view.all()
    for i, (o, a, r, d, o2, a2) in enumerate(ref):
        np.testing.assert_array_equal(b.observation[i], o)
        np.testing.assert_array_equal(b.next_observation[i], o2)
        assert b.action[i] == a and b.next_action[i] == a2
        np.testing.assert_allclose(b.reward[i], r, rtol=1e-5, atol=1e-6)
        assert b.discount[i] == np.float32(d)


def test_frame_pair_is_one_gather_of_stack_plus_n_frames(tmp_path, monkeypatch):
    """Observation and next observation come from one gather of k + n frames per row (they
    overlap), not two gathers of k."""
    import rlu.data.views as views

    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (9, 3, 2), dtype=np.uint8)
    first, last, term = np.zeros(9, bool), np.zeros(9, bool), np.zeros(9, bool)
    first[0], last[-1] = True, True
    disc = np.ones(9, np.float32)
    seg = Segment(frames, np.zeros(9, np.int64), np.zeros(9, np.float32), disc, first, last,
                  term, {}, None)  # fmt: skip
    ds = write(tmp_path, [seg], FRAME_SCHEMA)
    shapes = []
    real_take = views._take

    def counting_take(col, rows):
        shapes.append(np.shape(rows))
        return real_take(col, rows)

    monkeypatch.setattr(views, "_take", counting_take)
    for n in (1, 3):
        shapes.clear()
        TransitionView(ds, n_step=n).batch(np.arange(4))
        assert shapes == [(4, 4 + n)], (n, shapes)


def test_make_sampler_takes_a_batch_spec(tmp_path):
    from rlu.data import make_sampler
    from rlu.types import BatchSpec, RluError, SpecError

    rng = np.random.default_rng(1)
    n = 6
    first, last, term = np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, bool)
    first[0], last[-1] = True, True
    obs = {"a": rng.standard_normal((n, 2)).astype(np.float32),
           "cam": rng.integers(0, 256, (n, 3, 3, 2), dtype=np.uint8)}  # fmt: skip
    reward = np.array([3.0, -2.0, 0.5, 0.0, 7.0, 0.0], np.float32)
    seg = Segment(obs, np.zeros((n, 1), np.float32), reward, np.ones(n, np.float32), first,
                  last, term, {}, None)  # fmt: skip
    ds = write(tmp_path, [seg], DICT_SCHEMA)
    b = make_sampler(ds, BatchSpec(64, reward_clip=1.0), seed=0).sample()
    assert set(np.unique(b.reward)) <= {-1.0, 0.0, 0.5, 1.0}
    seq = make_sampler(ds, BatchSpec(2, "sequence", sequence_length=3), seed=0).sample()
    assert seq.mask.shape == (2, 3)
    with pytest.raises(RluError, match="BatchSpec"):
        make_sampler(ds, 64)
    with pytest.raises(SpecError, match="kind"):
        BatchSpec(8, "windows")
    with pytest.raises(SpecError, match="batch_size"):
        BatchSpec(0)


def test_frame_stack_at_episode_start_is_zero_padded(tmp_path):
    frames = np.arange(1, 4, dtype=np.uint8)[:, None, None] * np.ones((3, 3, 2), np.uint8)
    seg = Segment(
        frames,
        np.zeros(3, np.int64),
        np.zeros(3, np.float32),
        np.array([1, 1, 0], np.float32),
        np.array([1, 0, 0], bool),
        np.array([0, 0, 1], bool),
        np.zeros(3, bool),
    )
    ds = write(tmp_path, [seg], FRAME_SCHEMA)
    b = TransitionView(ds).all()
    # step 0: three zero frames then frame 1, newest last
    assert b.observation[0, 0, 0].tolist() == [0, 0, 0, 1]
    assert b.next_observation[1, 0, 0].tolist() == [0, 1, 2, 3]


@FAST
@given(
    segs=segments(frames=False),
    length=st.integers(1, 6),
    stride=st.integers(1, 3),
)
def test_sequences_equal_reference(tmp_path, segs, length, stride):
    ds = write(tmp_path, segs, DICT_SCHEMA)
    view = SequenceView(ds, length, stride, return_to_go=True, timestep=True)
    ref = []
    for seg in segs:
        T = len(seg)
        starts = list(range(0, max(T - 1, 1), stride))
        for t in starts:
            ref.append((seg, t))
    assert len(view) == len(ref)
    b = view.batch(np.arange(len(view)))
    for i, (seg, t) in enumerate(ref):
        for j in range(length):
            real = t + j < len(seg)
            assert b.mask[i, j] == real
            if real:
                np.testing.assert_array_equal(b.observation["a"][i, j], seg.observation["a"][t + j])
                np.testing.assert_array_equal(
                    b.observation["cam"][i, j], seg.observation["cam"][t + j]
                )
                assert b.reward[i, j] == seg.reward[t + j]
                assert b.is_last[i, j] == seg.is_last[t + j]
                rtg = np.float32(np.sum(seg.reward[t + j :], dtype=np.float64))
                assert b.return_to_go[i, j] == pytest.approx(rtg, rel=1e-6, abs=1e-6)
                assert b.timestep[i, j] == t + j
            else:
                assert b.reward[i, j] == 0 and not b.observation["cam"][i, j].any()
                assert b.return_to_go[i, j] == 0 and b.timestep[i, j] == 0


@FAST
@given(segs=segments(frames=True), length=st.integers(1, 5))
def test_sequence_frame_stacks(tmp_path, segs, length):
    ds = write(tmp_path, segs, FRAME_SCHEMA, "zlib")
    view = SequenceView(ds, length)
    b = view.batch(np.arange(len(view)))
    i = 0
    for seg in segs:
        for t in range(0, max(len(seg) - 1, 1)):
            for j in range(length):
                if t + j < len(seg):
                    np.testing.assert_array_equal(b.observation[i, j], obs_at(seg, t + j, 4))
            i += 1


def test_two_step_window_is_one_transition(tmp_path):
    """A release seq2 window (no episode boundary) gives exactly the loader's SARSA tuple."""
    obs = {"a": np.array([[1, 2], [3, 4]], np.float32), "cam": np.zeros((2, 3, 3, 2), np.uint8)}
    seg = Segment(
        obs,
        np.array([[0.5], [-0.5]], np.float32),
        np.array([0.25, 0.75], np.float32),
        np.array([1.0, 1.0], np.float32),
        np.zeros(2, bool),
        np.zeros(2, bool),
        np.zeros(2, bool),
    )
    b = TransitionView(write(tmp_path, [seg], DICT_SCHEMA)).all()
    assert b.reward.tolist() == [0.25] and b.discount.tolist() == [1.0]
    assert b.action.tolist() == [[0.5]] and b.next_action.tolist() == [[-0.5]]
    assert b.next_observation["a"].tolist() == [[3, 4]]


def test_sampler_is_seeded_and_epoch_covers_everything(tmp_path):
    from rlu.data import Sampler
    from rlu.data.synthetic import random_episodes

    segs = list(random_episodes(DICT_SCHEMA, 6, 7, seed=3, vary_length=True))
    ds = write(tmp_path, segs, DICT_SCHEMA)
    view = TransitionView(ds)
    a = Sampler(view, 5, seed=1).sample()
    b = Sampler(view, 5, seed=1).sample()
    c = Sampler(view, 5, seed=2).sample()
    np.testing.assert_array_equal(a.reward, b.reward)
    assert not np.array_equal(a.reward, c.reward)
    seen = np.concatenate([x.reward for x in Sampler(view, 4, seed=0).epoch()])
    np.testing.assert_array_equal(np.sort(seen), np.sort(view.all().reward))
    s = Sampler(view, 5, seed=9)
    state = s.get_state()
    first = s.sample().reward
    s.set_state(state)
    np.testing.assert_array_equal(s.sample().reward, first)


def test_empty_view_raises_clear_error(tmp_path):
    from rlu.data import Sampler
    from rlu.types import RluError

    seg = Segment(
        {"a": np.zeros((1, 2), np.float32), "cam": np.zeros((1, 3, 3, 2), np.uint8)},
        np.zeros((1, 1), np.float32),
        np.zeros(1, np.float32),
        np.zeros(1, np.float32),
        np.ones(1, bool),
        np.ones(1, bool),
        np.zeros(1, bool),
    )
    ds = write(tmp_path, [seg], DICT_SCHEMA)
    with pytest.raises(RluError, match="no TransitionView samples: it holds no segment of 2"):
        Sampler(TransitionView(ds), 4)


def test_n_step_longer_than_every_window_says_why_and_the_fix(tmp_path):
    """Converted 2-step windows (the control suite's release family) hold one transition each:
    a 5-step view of them is empty, and the error names the lengths and both fixes."""
    from rlu.data import Sampler
    from rlu.types import RluError

    def window(i):
        return Segment(
            {"a": np.full((2, 2), i, np.float32), "cam": np.zeros((2, 3, 3, 2), np.uint8)},
            np.zeros((2, 1), np.float32),
            np.ones(2, np.float32),
            np.ones(2, np.float32),
            np.array([True, False]),
            np.array([False, True]),
            np.zeros(2, bool),  # not terminal: the window is cut from a longer episode
        )

    ds = write(tmp_path, [window(i) for i in range(3)], DICT_SCHEMA)
    assert len(TransitionView(ds, n_step=1)) == 3
    with pytest.raises(RluError) as err:
        Sampler(TransitionView(ds, n_step=5, gamma=0.99), 4)
    message = str(err.value)
    assert "no TransitionView samples" in message and "\n" not in message
    assert "a 5-step transition needs 6 steps" in message and "longest segment holds 2" in message
    assert "n_step <= 1" in message and "dm_control_suite_episodes" in message


@settings(max_examples=60, deadline=None)
@given(counts=st.lists(st.integers(0, 50), min_size=1, max_size=40).filter(lambda c: sum(c) > 0))
def test_index_locate_equals_binary_search(counts):
    """The guide-table lookup agrees with a plain binary search, zero-count and very uneven
    segments included (the fallback path)."""
    from rlu.data.views import _Index

    class FakeDs:
        start = np.concatenate([[0], np.cumsum(np.asarray(counts) + 1)[:-1]])

    index = _Index(FakeDs, np.asarray(counts))
    ids = np.arange(index.size)
    seg, step = index.locate(ids)
    want = np.searchsorted(index.cum, ids, side="right") - 1
    np.testing.assert_array_equal(seg, want)
    np.testing.assert_array_equal(step, FakeDs.start[want] + ids - index.cum[want])
