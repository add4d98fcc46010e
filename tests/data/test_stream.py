"""The stream sampler: the views' exact values for the samples it draws, every sample drawn
``reuse`` times per pass, batches independent of threads, resume, mixtures, open files, memory,
hostile frames. Tiny real-format datasets written by rlu's writer in tmp_path."""

from __future__ import annotations

import dataclasses
import io
import os
import threading
import zlib

import numpy as np
import pytest

from rlu.data import (
    DatasetWriter,
    Schema,
    Segment,
    SequenceView,
    StreamSampler,
    TransitionView,
    open_dataset,
    stream_sampler,
)
from rlu.data import stream as stream_module
from rlu.types import ArraySpec, BatchSpec, BoundedSpec, DiscreteSpec, FormatError, RluError

FRAMES = Schema(ArraySpec((6, 5), "uint8"), DiscreteSpec((), "int64", 4), frame_stack=4,
                image_encoding="zlib", task_id="atari/Pong")  # fmt: skip
DICT = Schema({"a": ArraySpec((2,), "float32"), "b": ArraySpec((3,), "float64")},
              BoundedSpec((1,), "float32"), task_id="control_suite/cartpole_swingup")  # fmt: skip


def segments(rng: np.random.Generator, n: int, frames: bool) -> list[Segment]:
    """Episodes ending in a terminal state or a truncation, and bare windows (no first step),
    of 1 to 40 steps."""
    out = []
    for _ in range(n):
        t = int(rng.choice([1, 2, 3, 7, 19, 40]))
        kind = rng.choice(["terminal", "truncated", "window"])
        first, last, term = np.zeros(t, bool), np.zeros(t, bool), np.zeros(t, bool)
        disc = np.ones(t, np.float32)
        if kind != "window":
            first[0], last[-1], disc[-1] = True, True, 0.0
            if kind == "terminal":
                term[-1] = True
                disc[max(t - 2, 0)] = 0.0
        reward = rng.standard_normal(t).astype(np.float32) * 3
        if frames:
            obs = rng.integers(0, 256, (t, 6, 5), dtype=np.uint8)
            action = rng.integers(0, 4, t).astype(np.int64)
            prefix = None if first[0] else rng.integers(0, 256, (3, 6, 5), dtype=np.uint8)
        else:
            obs = {"a": rng.standard_normal((t, 2)).astype(np.float32),
                   "b": rng.standard_normal((t, 3))}  # fmt: skip
            action = rng.uniform(-1, 1, (t, 1)).astype(np.float32)
            prefix = None
        out.append(Segment(obs, action, reward, disc, first, last, term, {}, prefix))
    return out


def write(path, schema: Schema, seed: int, n: int = 30):
    with DatasetWriter(path, schema) as w:
        for s in segments(np.random.default_rng(seed), n, schema.frame_stack > 1):
            w.append(s)
    return path


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("stream")
    return {
        "frames": write(root / "frames", FRAMES, 0, 60),
        "dict": write(root / "dict", DICT, 1, 60),
        "mix": [write(root / f"mix{i}", FRAMES, 10 + i, 12 + 4 * i) for i in range(3)],
    }


def equal(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(equal(a[k], b[k]) for k in a)
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)


SPECS = [
    BatchSpec(16),
    BatchSpec(16, n_step=3, gamma=0.9, reward_clip=1.0),
    BatchSpec(16, kind="sequence", sequence_length=5, return_to_go=True, timestep=True),
    BatchSpec(16, kind="sequence", sequence_length=1),
]


@pytest.mark.parametrize("spec", SPECS, ids=["sarsa", "nstep", "seq_rtg", "seq1"])
@pytest.mark.parametrize("kind", ["frames", "dict"])
def test_batches_are_the_views_values(data, spec, kind):
    ds = open_dataset(data[kind])
    view = (SequenceView(ds, spec.sequence_length, return_to_go=spec.return_to_go,
                         timestep=spec.timestep)
            if spec.kind == "sequence" else
            TransitionView(ds, spec.n_step, spec.gamma, spec.reward_clip))  # fmt: skip
    with StreamSampler(data[kind], spec, seed=3, memory=60_000, reuse=2, chunk=7) as s:
        assert s.window < len(view)  # the buffer holds part of the dataset only
        for _ in range(40):
            batch, source = s.sample_sourced()
            assert (source.dataset == 0).all() and (source.task == 0).all()
            want = view.batch(source.index)
            for name, got, ref in zip(batch._fields, batch, want, strict=True):
                assert equal(got, ref), name


def test_every_sample_drawn_reuse_times_per_pass(data):
    """Coverage: pass 0's samples are each drawn exactly ``reuse`` times, then pass 1 follows;
    uniform draws of as many samples miss about a third of them."""
    n = len(TransitionView(open_dataset(data["frames"])))
    reuse, batch = 3, 16
    with StreamSampler(data["frames"], BatchSpec(batch), seed=1, memory=60_000, reuse=reuse,
                       chunk=7) as s:  # fmt: skip
        counts = np.zeros(n, np.int64)
        epochs = []
        for _ in range(2 * reuse * n // batch):
            _, src = s.sample_sourced()
            np.add.at(counts, src.index[src.epoch == 0], 1)
            epochs.append(src.epoch)
            if counts.sum() == reuse * n:
                break
        assert (counts == reuse).all()
        assert np.concatenate(epochs).max() == 1  # the next pass had begun: the stream goes on
    uniform = np.bincount(np.random.default_rng(0).integers(0, n, reuse * n), minlength=n)
    assert (uniform == 0).mean() > 0.02 and (uniform != reuse).mean() > 0.5


def test_batches_spread_over_episodes(data):
    """A batch draws from the whole window: about as many episodes as a uniform batch."""
    ds = open_dataset(data["frames"])
    view = TransitionView(ds)
    with StreamSampler(data["frames"], BatchSpec(32), seed=0, memory=400_000, chunk=8) as s:
        assert s.window == len(view)  # the window covers the whole dataset
        stream = [len(np.unique(view.index.locate(s.sample_sourced()[1].index)[0]))
                  for _ in range(50)]  # fmt: skip
    rng = np.random.default_rng(0)
    uniform = [len(np.unique(view.index.locate(rng.integers(0, len(view), 32))[0]))
               for _ in range(50)]  # fmt: skip
    assert np.mean(stream) >= 0.9 * np.mean(uniform)


def test_batches_do_not_depend_on_threads(data):
    spec = BatchSpec(16, n_step=2, gamma=0.99)
    runs = []
    for workers in (1, 4):
        with StreamSampler(data["mix"], spec, seed=5, memory=40_000, workers=workers,
                           chunk=5) as s:  # fmt: skip
            runs.append([s.sample() for _ in range(30)])
    for a, b in zip(*runs, strict=True):
        assert all(equal(x, y) for x, y in zip(a, b, strict=True))
    with StreamSampler(data["mix"], spec, seed=6, memory=40_000, chunk=5) as s:
        other = s.sample()
    assert not equal(other.observation, runs[0][0].observation)


@pytest.mark.parametrize("kind", ["transition", "sequence"])
def test_resume_continues_the_same_batches(data, kind):
    import torch

    spec = BatchSpec(8, kind=kind, sequence_length=4, return_to_go=kind == "sequence")
    with StreamSampler(data["mix"], spec, seed=2, memory=40_000, chunk=6) as s:
        for _ in range(37):
            s.sample()
        buf = io.BytesIO()
        torch.save({"sampler": s.get_state()}, buf)  # as a checkpoint holds it
        want = [s.sample_sourced() for _ in range(25)]
    buf.seek(0)
    state = torch.load(buf, weights_only=True)["sampler"]
    with StreamSampler(data["mix"], spec, seed=2, memory=40_000, chunk=6) as t:
        t.sample()  # anywhere: set_state replaces it
        t.set_state(state)
        got = [t.sample_sourced() for _ in range(25)]
    for (a, sa), (b, sb) in zip(want, got, strict=True):
        assert all(equal(x, y) for x, y in zip(a, b, strict=True))
        assert all(np.array_equal(x, y) for x, y in zip(sa, sb, strict=True))


def test_bad_states_are_refused(data):
    with StreamSampler(data["frames"], BatchSpec(4), memory=60_000, chunk=7) as s:
        for bad in ({"bit_generator": {}}, {"stream": 1, "tail": {}, "bucket": 0, "offset": 0},
                    {**s.get_state(), "bucket": -1}):  # fmt: skip
            with pytest.raises((ValueError, KeyError)):
                s.set_state(bad)


def test_mixture_weights_and_sources(data, tmp_path):
    other = write(tmp_path / "cartpole", dataclasses.replace(FRAMES, task_id="atari/Breakout"), 7)
    paths = [*data["mix"], other]
    weights = [0.4, 0.3, 0.2, 0.1]
    with StreamSampler(paths, BatchSpec(64), seed=0, weights=weights, memory=80_000,
                       chunk=6) as s:  # fmt: skip
        assert s.tasks == ["atari/Pong", "atari/Breakout"]
        got = [s.sample_sourced()[1] for _ in range(150)]
    d = np.concatenate([g.dataset for g in got])
    share = np.bincount(d, minlength=4) / len(d)
    assert np.abs(share - weights).max() < 0.02, share
    task = np.concatenate([g.task for g in got])
    assert np.array_equal(task, (d == 3).astype(np.int64))
    per_batch = [len(np.unique(g.dataset)) for g in got]
    assert np.mean(per_batch) > 3.5  # every batch mixes the datasets


def test_open_files_are_bounded(data, tmp_path):
    """No file stays open between reads (no memory maps kept); at most ``workers`` at once."""
    paths = [write(tmp_path / f"d{i}", FRAMES, 100 + i, 6) for i in range(12)]
    before = len(os.listdir("/proc/self/fd"))
    inflight, peak, lock = [0], [0], threading.Lock()
    real = stream_module._pread_into

    def counted(*args, **kwargs):
        with lock:
            inflight[0] += 1
            peak[0] = max(peak[0], inflight[0])
        try:
            return real(*args, **kwargs)
        finally:
            with lock:
                inflight[0] -= 1

    stream_module._pread_into = counted
    try:
        with StreamSampler(paths, BatchSpec(32), memory=60_000, workers=3, chunk=4) as s:
            assert len(os.listdir("/proc/self/fd")) == before
            for _ in range(40):
                s.sample()
    finally:
        stream_module._pread_into = real
    assert 1 <= peak[0] <= 3


def test_memory_bounds_the_buffer(data):
    with StreamSampler(data["frames"], BatchSpec(8), memory=30_000, chunk=4) as s:
        ring = sum(a.nbytes for a in (*s._ring.values(), *s._slot.values()))
        assert ring <= 30_000 and s.window >= 8
    with pytest.raises(RluError, match="give more memory"):
        StreamSampler(data["frames"], BatchSpec(64), memory=5_000)


def test_refusals(data, tmp_path):
    with pytest.raises(RluError, match="one schema"):
        StreamSampler([data["frames"], data["dict"]], BatchSpec(4))
    with pytest.raises(RluError, match="one positive number per dataset"):
        StreamSampler(data["mix"], BatchSpec(4), weights=[1, 0, 1])
    with pytest.raises(RluError, match="reward_clip"):
        stream_sampler(data["frames"], 4, kind="sequence", length=3, reward_clip=1.0)
    with pytest.raises(RluError, match="reuse"):
        StreamSampler(data["frames"], BatchSpec(4), reuse=0)
    with pytest.raises(RluError, match="needs length"):
        stream_sampler(data["frames"], 4, kind="sequence")


def test_a_bad_frame_fails_the_batch_that_draws_it(tmp_path):
    path = write(tmp_path / "bad", FRAMES, 3, 8)
    ds = open_dataset(path)
    zpath = path / "steps" / "observation.zlib"
    offsets = np.fromfile(path / "steps" / "observation.offsets.bin", "<i8")
    blob = zlib.compress(bytes(30), 9)  # a stream of the wrong size, of the same length
    a, b = int(offsets[5]), int(offsets[6])
    data = bytearray(zpath.read_bytes())
    data[a:b] = (blob + bytes(b - a))[: b - a] if len(blob) <= b - a else blob[: b - a]
    zpath.write_bytes(bytes(data))
    del ds
    s = StreamSampler(path, BatchSpec(4), memory=60_000, chunk=4)
    with pytest.raises(FormatError, match=r"observation\.zlib: frame 5 "):
        for _ in range(200):
            s.sample()
    s.close()
