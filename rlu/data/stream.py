"""Streaming batches from datasets larger than memory, and mixtures of many datasets.

:class:`StreamSampler` gives the batches of the uniform samplers (:class:`rlu.types.Transition`,
n-step and ``reward_clip`` honoured, or :class:`rlu.types.Sequence` with masks and the return to
go; the values of ``rlu.data.TransitionView`` / ``SequenceView`` for the same samples, exactly)
from one dataset or a weighted mixture of many, reading each dataset's files sequentially in
large blocks and holding a bounded buffer of decoded frames in RAM (docs/data.md, "Streaming").

How it works:

- **Chunks.** A dataset's samples (the view's eligible starts, in file order) are cut into chunks
  of ``chunk`` consecutive samples. A chunk is read in one piece per column (one ``pread`` of its
  zlib streams, one of each step column) and decoded by background threads into a ring buffer of
  rows (frames, with each step's columns at its newest frame's row). Each pass over a dataset
  visits its chunks in a fresh seeded random order; a mixture interleaves the datasets' chunk
  streams so that dataset ``d`` supplies a share ``weights[d]`` of the samples (the dataset whose
  supply is furthest behind its share goes next).
- **The sample stream.** Chunks laid end to end give every sample a position ``j`` in the stream.
  Each sample is drawn exactly ``reuse`` times, at times ``tau = j + window * u`` with ``u``
  uniform in [0, 1) (one ``u`` per draw); batches are the draws in the order of their times.
  Every draw at time ``tau`` comes from a sample within the ``window`` positions before it, so the
  buffer needs only the chunks that overlap the last ``window`` positions (plus the chunks being
  decoded ahead), and a batch is a uniform draw from those ``window`` samples: many episodes and,
  in a mixture, many datasets per batch. The first ``window`` positions draw their times at the
  window's end, in random order, so the first batches already spread over a whole window.
- **Every step once per pass.** Each sample of each pass is drawn exactly ``reuse`` times; the
  uniform sampler draws a sample Poisson(1) times per ``len(view)`` draws (37 % never).
- **Determinism.** The batches are a function of the datasets, the weights, the batch spec, the
  seed, ``memory`` (which sets ``window``), ``reuse`` and ``chunk``; never of ``workers`` or of
  thread timing: the threads only decode chunks whose place and content are fixed in advance,
  and a batch waits for the chunks it draws from.
- **Resume.** :meth:`get_state` is a few integers (the oldest chunk in the buffer and where the
  stream stands); :meth:`set_state` rebuilds the buffer from there and continues with the same
  batches (the training loop checkpoints it as it does the uniform sampler's generator).
- **Memory.** ``memory`` bytes of ring buffers, allocated once (touched as they fill), plus each
  dataset's segment index and chunk table (tens of bytes a segment), plus the batches in flight.
  Files are opened for one read and closed: at most ``workers`` are open at once, however many
  datasets the mixture holds.

The batch is the agent's named tuple; where each sample came from (its dataset, the dataset's
task, its index in the dataset's view, its pass) is :class:`SampleSource`, from
:meth:`StreamSampler.sample_sourced` (multi-game agents read the task index there: the batch types
every agent consumes stay as they are).
"""

from __future__ import annotations

import os
import stat
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, NamedTuple, TypedDict

import numpy as np

from rlu.data.inflate import inflate_frames
from rlu.data.store import Dataset, open_dataset
from rlu.data.views import n_step_counts, n_step_targets
from rlu.types import ArraySpec, BatchSpec, DiscreteSpec, FormatError, RluError, Transition
from rlu.types import Sequence as SequenceBatch

DEFAULT_MEMORY = 2 << 30
"""Bytes of decoded rows the stream sampler holds by default (2 GiB: ~290k Atari frames)."""
DEFAULT_REUSE = 8
"""Draws of each sample per pass by default (the decoding then runs at 1/8 of the batch rate)."""
DEFAULT_CHUNK = 1024
"""Samples per chunk (one sequential read per column) by default."""
_TAG_ORDER, _TAG_TIMES, _TAG_START = 1, 2, 3  # seed streams: chunk orders, draw times, first window
_STEP_COLUMNS = ("action", "reward", "discount", "is_first", "is_last")
_RECREATE = "re-create the dataset (re-run the command that wrote it)"


class SampleSource(NamedTuple):
    """Where each sample of a batch came from (leading axis = batch)."""

    dataset: np.ndarray
    """Index of the sample's dataset in ``StreamSampler.paths`` (int64)."""
    task: np.ndarray
    """Index of its dataset's task in ``StreamSampler.tasks`` (int64): the game id of a
    multi-game agent."""
    index: np.ndarray  # type: ignore[assignment]  # shadows tuple.index: the public field name
    """Its index in its dataset's ``TransitionView`` / ``SequenceView`` (int64)."""
    epoch: np.ndarray
    """The pass over its dataset it was drawn in (int64)."""


class _Column(NamedTuple):
    path: Path
    size: int
    dtype: np.dtype
    shape: tuple[int, ...]
    zlib: bool
    offsets: Path | None


class _Source:
    """What the sampler keeps of one dataset: its segment index and chunk table in RAM, and the
    files to read (the dataset's memory maps are dropped once this is built)."""

    def __init__(self, ds: Dataset, spec: BatchSpec, chunk: int):
        self.path, self.schema = ds.path, ds.schema
        self.task = ds.schema.task_id or str(ds.path)
        k = self.k = ds.schema.frame_stack
        start = np.array(ds.start, np.int64)
        length = np.array(ds.length, np.int64)
        self.start, self.last = start, start + length - 1
        # row of step s of segment g: s + self.row_offset[g] (its newest frame for Atari)
        self.row_offset = np.array(ds.frame_start, np.int64) + k - 1 - start if k > 1 else 0 * start
        self.sequence = spec.kind == "sequence"
        if self.sequence:
            self.stride, self.extra = 1, spec.sequence_length - 1
            counts = (np.maximum(length - 2, 0) // self.stride) + 1
        else:
            self.stride, self.extra = 1, spec.n_step
            terminal = np.asarray(ds.column("is_terminal"))[self.last] if spec.n_step > 1 else None
            counts = n_step_counts(length, terminal, spec.n_step)
        self.cum = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.size = int(self.cum[-1])
        self.chunks = -(-self.size // chunk)
        self.chunk = chunk
        self.columns = self._columns(ds)
        self.cum_reward: np.ndarray | None = None
        if spec.return_to_go:  # the running sum of SequenceView, at each chunk's first step
            self.cum_reward, self.cum_end = self._running_sums(ds)

    def _columns(self, ds: Dataset) -> dict[str, _Column]:
        schema, out = ds.schema, {}
        frames = schema.frame_columns()
        names = {**{n: s for n, s in schema.step_columns().items() if not n.startswith("is_t")},
                 **frames}  # fmt: skip
        for name, spec in names.items():
            if name in ("is_first", "is_last") and not self.sequence:
                continue
            zlib = schema.encoding(spec) == "zlib"
            rel = f"steps/{name}.zlib" if zlib else f"steps/{name}.bin"
            path = ds.file(rel)
            offsets = ds.file(f"steps/{name}.offsets.bin") if zlib else None
            if zlib:
                ds.column(name)  # the offsets checked once, here (ZlibColumn)
            dtype = np.dtype(spec.dtype).newbyteorder("<")
            out[name] = _Column(path, os.stat(path).st_size, dtype, tuple(spec.shape), zlib,
                                offsets)  # fmt: skip
        return out

    def _running_sums(self, ds: Dataset) -> tuple[np.ndarray, np.ndarray]:
        """SequenceView's running sum of the rewards (``cum[i]``: rewards of steps < i, the same
        sequential float64 additions) at each chunk's first step and past each segment's last."""
        reward = ds.column("reward")
        first = self.chunk_steps(np.arange(self.chunks))[0]
        at = np.concatenate([first, self.last + 1])
        values = np.zeros(len(at), np.float64)
        carry, block = 0.0, 1 << 22
        for a in range(0, len(reward), block):
            part = np.asarray(reward[a : a + block])
            cum = np.cumsum(np.concatenate([[carry], part]), dtype=np.float64)  # cum[a..a+n]
            sel = (at >= a) & (at <= a + len(part))
            values[sel] = cum[at[sel] - a]
            carry = float(cum[-1])
        return values[: len(first)], values[len(first) :]

    # -- chunk geometry ------------------------------------------------------------------------
    def locate(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(segment, step) of the view's samples ``ids``."""
        seg = np.searchsorted(self.cum, ids, side="right") - 1
        return seg, self.start[seg] + (ids - self.cum[seg]) * self.stride

    def chunk_ids(self, c: int) -> tuple[int, int]:
        return c * self.chunk, min((c + 1) * self.chunk, self.size)

    def chunk_steps(self, chunks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(first step, one past the last step) each chunk reads."""
        lo_ids = chunks * self.chunk
        hi_ids = np.minimum(lo_ids + self.chunk, self.size) - 1
        _, s_lo = self.locate(lo_ids)
        seg, t_e = self.locate(hi_ids)
        return s_lo, np.minimum(t_e + self.extra, self.last[seg]) + 1

    def chunk_rows(self, chunks: np.ndarray) -> np.ndarray:
        """Rows of the ring each chunk takes (frames, with each step at its newest frame)."""
        s_lo, s_hi = self.chunk_steps(chunks)
        g_lo = np.searchsorted(self.start, s_lo, side="right") - 1
        g_hi = np.searchsorted(self.start, s_hi - 1, side="right") - 1
        return (s_hi - 1 + self._off(g_hi)) - (s_lo + self._off(g_lo)) + self.k

    def _off(self, seg: np.ndarray) -> np.ndarray:
        return self.row_offset[seg]


class _Instance:
    """One chunk in the sample stream: what it is, where it lies, when its draws fall."""

    __slots__ = ("index", "source", "chunk", "epoch", "pos", "n", "row", "rows", "slot",
                 "order", "times", "future", "snapshot")  # fmt: skip
    index: int
    source: int
    chunk: int
    epoch: int
    pos: int
    n: int
    row: int
    rows: int
    slot: int
    order: np.ndarray
    times: np.ndarray
    future: Future[None]
    snapshot: _Plan

    def __init__(self, **kw: Any):
        for k, v in kw.items():
            setattr(self, k, v)


class _Plan(TypedDict):
    """Where the planning of the stream stands: the next chunk's instance number and stream
    position, and per dataset its pass, its next chunk in that pass's order and its supply."""

    instance: int
    pos: int
    epoch: list[int]
    k: list[int]
    supplied: list[int]


def _copy_plan(p: Mapping[str, Any]) -> _Plan:
    return _Plan(instance=int(p["instance"]), pos=int(p["pos"]), epoch=list(p["epoch"]),
                 k=list(p["k"]), supplied=list(p["supplied"]))  # fmt: skip


class _Ring:
    """First-in first-out allocation of contiguous ranges in a ring of ``size`` entries (a range
    that would cross the end starts again at 0; the entries skipped are lost until then)."""

    def __init__(self, size: int):
        self.size = size
        self.live: deque[tuple[int, int]] = deque()  # (start, length) of ranges not yet freed

    def alloc(self, n: int) -> int | None:
        """The start of ``n`` free entries after the newest range, or None (no room yet)."""
        if n > self.size:
            return None
        if not self.live:
            start: int | None = 0
        else:
            tail, (last, length) = self.live[0][0], self.live[-1]
            head = last + length
            if head > tail:  # in use: [tail, head)
                start = head if head + n <= self.size else (0 if n <= tail else None)
            else:  # in use: [tail, size) and [0, head)
                start = head if head + n <= tail else None
        if start is not None:
            self.live.append((start, n))
        return start

    def free_oldest(self) -> None:
        self.live.popleft()


class StreamSampler:
    """Batches of ``spec`` streamed from ``datasets`` (paths or opened datasets; a mixture when
    several), weighted by ``weights`` (default: by their sizes, i.e. uniform over all samples), in
    at most ``memory`` bytes of decoded rows. See the module docstring for the sampling
    distribution, determinism and resume; ``workers`` threads decode (default: one per core)."""

    def __init__(
        self,
        datasets: str | os.PathLike | Dataset | Sequence[str | os.PathLike | Dataset],
        spec: BatchSpec,
        seed: int = 0,
        weights: Sequence[float] | None = None,
        memory: int = DEFAULT_MEMORY,
        reuse: int = DEFAULT_REUSE,
        workers: int | None = None,
        chunk: int = DEFAULT_CHUNK,
    ):
        if not isinstance(spec, BatchSpec):
            raise RluError(f"StreamSampler takes a rlu.types.BatchSpec, got {type(spec).__name__}")
        if isinstance(datasets, str | os.PathLike | Dataset):
            datasets = [datasets]
        if not datasets:
            raise RluError("StreamSampler needs at least one dataset")
        checks = [("reuse", reuse), ("chunk", chunk), ("memory", memory), ("workers", workers or 1)]
        for name, value in checks:
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
                raise RluError(f"stream sampler {name}={value!r}; give an integer >= 1")
        if spec.kind == "sequence" and spec.reward_clip is not None:
            raise RluError(
                "BatchSpec.reward_clip is applied by transition batches only; clip sequence "
                "rewards in the agent"
            )
        from rlu.seeds import seed_stream

        seed_stream(seed)  # a bad seed fails here
        self.spec, self.seed, self.batch_size = spec, int(seed), spec.batch_size
        self.reuse, self.chunk = int(reuse), int(chunk)
        self.sources: list[_Source] = []
        for d in datasets:
            ds = open_dataset(d) if isinstance(d, str | os.PathLike) else d
            self.sources.append(_Source(ds, spec, self.chunk))
            del ds
        self.paths = [s.path for s in self.sources]
        self.tasks = list(dict.fromkeys(s.task for s in self.sources))
        self._task_of = np.array([self.tasks.index(s.task) for s in self.sources], np.int64)
        self._check_schemas()
        empty = [str(s.path) for s in self.sources if s.size == 0]
        if empty:
            why = "it holds no segment" if spec.kind == "sequence" else (
                f"a transition needs {spec.n_step + 1} steps of one segment, or a terminal "
                "inside its window"
            )  # fmt: skip
            rest = "; leave it out of the mixture" if len(self.sources) > 1 else ""
            raise RluError(f"{empty[0]}: the dataset has no {spec.kind} samples ({why}){rest}")
        sizes = np.array([s.size for s in self.sources], np.float64)
        if weights is None:
            w = sizes
        else:
            try:
                w = np.asarray(weights, np.float64)
            except (TypeError, ValueError):
                w = np.zeros(0)
            if w.shape != sizes.shape or not np.isfinite(w).all() or (w <= 0).any():
                raise RluError(
                    f"weights {weights!r}: give one positive number per dataset "
                    f"({len(sizes)} datasets)"
                )
        self.weights = w / w.sum()
        self._layout(int(memory))
        self.workers = int(workers or _cores())
        self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="rlu-stream")
        self._closed = False
        self._reset(self._start_snapshot(), self.window // self.bucket, 0)

    # -- layout --------------------------------------------------------------------------------
    def _check_schemas(self) -> None:
        first = self.sources[0].schema
        for s in self.sources[1:]:
            a, b = first.action, s.schema.action
            same_action = a == b or (
                isinstance(a, DiscreteSpec) and isinstance(b, DiscreteSpec)
                and (a.shape, a.dtype) == (b.shape, b.dtype)
            )  # fmt: skip
            if (s.schema.observation != first.observation or not same_action
                    or s.schema.frame_stack != first.frame_stack):  # fmt: skip
                raise RluError(
                    f"{s.path}: its schema ({s.schema.observation}, {s.schema.action}, frame "
                    f"stack {s.schema.frame_stack}) differs from {self.sources[0].path}'s; a "
                    "mixture samples datasets of one schema (discrete actions may differ in "
                    "their number of values: the games of an Atari mixture)"
                )
        self.schema = first
        nums = [s.schema.action.num_values for s in self.sources
                if isinstance(s.schema.action, DiscreteSpec)]  # fmt: skip
        self.action_spec = first.action
        # with nums, every action is discrete (same_action above)
        if nums and isinstance(first.action, DiscreteSpec) and max(nums) != first.action.num_values:
            self.action_spec = next(a for s in self.sources if isinstance(a := s.schema.action,
                                    DiscreteSpec) and a.num_values == max(nums))  # fmt: skip

    def _ring_columns(self) -> tuple[dict[str, tuple], dict[str, str]]:
        """The ring's columns per row (name: (shape, dtype)) and the slots' (name: dtype)."""
        rows: dict[str, tuple] = {}
        for name, col in self.sources[0].columns.items():
            if name.startswith("observation") or name == "action" or self.spec.kind == "sequence":
                rows[name] = (col.shape, col.dtype)
        if self.spec.return_to_go:
            rows["return_to_go"] = ((), np.dtype(np.float32))
        if self.spec.timestep:
            rows["timestep"] = ((), np.dtype(np.int64))
        slots = {"row": "int64", "source": "int64", "index": "int64", "epoch": "int64"}
        if self.spec.kind == "transition":
            slots |= {"gap": "int32", "reward": "float32", "discount": "float32"}
        else:
            slots["valid"] = "int64"
        return rows, slots

    def _layout(self, memory: int) -> None:
        """Ring size from ``memory``; the window and bucket of the sample stream."""
        rows, slots = self._ring_columns()
        per_row = sum(int(np.prod(shape, dtype=np.int64)) * np.dtype(dt).itemsize
                      for shape, dt in rows.values())  # fmt: skip
        per_row += sum(np.dtype(dt).itemsize for dt in slots.values())  # a slot per row at most
        self.capacity = memory // per_row
        ratio, longest, most = 1.0, 1, 1  # rows per sample; rows and samples of a chunk
        for s in self.sources:
            c = np.arange(s.chunks)
            n = np.minimum(c * s.chunk + s.chunk, s.size) - c * s.chunk
            r = s.chunk_rows(c)
            ratio = max(ratio, float((r / n).max()))
            longest, most = max(longest, int(r.max())), max(most, int(n.max()))
        # at a bucket's start the buffer holds the chunks overlapping window + bucket positions,
        # one more at each end, and one chunk's rows lost at the ring's end; a quarter of what
        # is left decodes ahead
        avail = int((self.capacity - 2 * longest) / ratio) - 2 * most - 4
        window = int(0.75 * avail / (1 + 1 / 16))
        least = max(self.batch_size, most)
        if window < least:
            need = (least * (1 + 1 / 16) / 0.75 + 2 * most + 4) * ratio + 2 * longest
            raise RluError(
                f"stream sampler memory={memory:,} bytes holds {self.capacity:,} rows of "
                f"{per_row:,} bytes; a window of {least:,} samples (a batch, or a chunk) needs "
                f"{int(need * per_row) + 1:,}: give more memory (or a smaller chunk)"
            )
        total = int(sum(s.size for s in self.sources))
        self.window = min(window, total)
        self.bucket = max(1, self.window // 16)
        self.per_row = per_row

    # -- state ---------------------------------------------------------------------------------
    def _start_snapshot(self) -> _Plan:
        d = len(self.sources)
        return _Plan(instance=0, pos=0, epoch=[0] * d, k=[0] * d, supplied=[0] * d)

    def _reset(self, snapshot: Mapping[str, Any], bucket: int, offset: int) -> None:
        """Empty the buffer; plan chunks from ``snapshot`` on; draw from bucket ``bucket``,
        offset ``offset`` of its draws."""
        self._drain()
        self._plan = _copy_plan(snapshot)
        self._orders: dict[tuple[int, int], np.ndarray] = {}
        self._live: deque[_Instance] = deque()
        self._rows = _Ring(self.capacity)
        self._slots = _Ring(self.capacity)
        self._bucket, self._offset = bucket, offset
        self._draws: np.ndarray | None = None  # slots of the current bucket's draws, in order
        self._emitted = 0
        self._alloc_rings()

    def _alloc_rings(self) -> None:
        if getattr(self, "_ring", None) is not None:
            return
        rows, slots = self._ring_columns()
        cap = self.capacity
        self._ring = {k: np.empty((cap, *shape), dt) for k, (shape, dt) in rows.items()}
        self._slot = {k: np.empty(cap, dt) for k, dt in slots.items()}

    def get_state(self) -> dict:
        """Where the stream stands (plain integers: a checkpoint's ``sampler`` entry)."""
        tail = self._live[0].snapshot if self._live else self._plan
        return {"stream": 1, "tail": dict(_copy_plan(tail)),
                "bucket": int(self._bucket), "offset": int(self._offset)}  # fmt: skip

    def set_state(self, state: Mapping[str, Any]) -> None:
        """Continue from a state of :meth:`get_state` (same datasets, spec, seed, memory)."""
        if not isinstance(state, Mapping) or state.get("stream") != 1:
            raise ValueError("not a stream sampler's state (another sampler wrote it)")
        tail, d = state["tail"], len(self.sources)
        ints = [tail["instance"], tail["pos"], state["bucket"], state["offset"]]
        lists = [tail["epoch"], tail["k"], tail["supplied"]]
        if any(isinstance(v, bool) or not isinstance(v, int) or v < 0 for v in ints) or any(
            not isinstance(v, list) or len(v) != d
            or any(isinstance(x, bool) or not isinstance(x, int) or x < 0 for x in v)
            for v in lists
        ):  # fmt: skip
            raise ValueError(f"a stream state for {d} datasets holds other values")
        self._reset(tail, state["bucket"], state["offset"])

    # -- planning ------------------------------------------------------------------------------
    def _order(self, d: int, epoch: int) -> np.ndarray:
        key = (d, epoch)
        if key not in self._orders:
            from rlu.seeds import seed_stream

            rng = np.random.default_rng(seed_stream(self.seed, _TAG_ORDER, d, epoch))
            self._orders = {k: v for k, v in self._orders.items() if k[0] != d or k[1] >= epoch - 1}
            self._orders[key] = rng.permutation(self.sources[d].chunks)
        return self._orders[key]

    def _next(self) -> _Instance | None:
        """Plan the next chunk of the stream, if the rings have room for it."""
        p = self._plan
        d = int(np.argmin(np.asarray(p["supplied"], np.float64) / self.weights))
        src = self.sources[d]
        c = int(self._order(d, p["epoch"][d])[p["k"][d]])
        lo, hi = src.chunk_ids(c)
        n = hi - lo
        rows = int(src.chunk_rows(np.array([c]))[0])
        row = self._rows.alloc(rows)
        if row is None:
            return None
        slot = self._slots.alloc(n)
        if slot is None:
            self._rows.live.pop()
            return None
        snapshot = _copy_plan(p)
        inst = _Instance(index=p["instance"], source=d, chunk=c, epoch=p["epoch"][d], pos=p["pos"],
                         n=n, row=row, rows=rows, slot=slot, snapshot=snapshot)  # fmt: skip
        self._draw_times(inst)
        p["instance"] += 1
        p["pos"] += n
        p["supplied"][d] += n
        p["k"][d] += 1
        if p["k"][d] == src.chunks:
            p["k"][d], p["epoch"][d] = 0, p["epoch"][d] + 1
        inst.future = self._pool.submit(self._decode, inst)
        self._live.append(inst)
        return inst

    def _draw_times(self, inst: _Instance) -> None:
        from rlu.seeds import seed_stream

        rng = np.random.default_rng(seed_stream(self.seed, _TAG_TIMES, inst.index))
        m = self.window
        times = (inst.pos + np.arange(inst.n, dtype=np.float64))[:, None] + m * rng.random(
            (inst.n, self.reuse)
        )
        if inst.pos < m:  # the first window: its draws fall at the window's end, in random order
            late = np.random.default_rng(seed_stream(self.seed, _TAG_START, inst.index))
            early = times < m
            times[early] = m + late.random(int(early.sum()))
        flat = times.ravel()
        order = np.argsort(flat, kind="stable")
        inst.times, inst.order = flat[order], order // self.reuse  # sample of each draw

    # -- decoding (worker threads) -------------------------------------------------------------
    def _decode(self, inst: _Instance) -> None:
        src = self.sources[inst.source]
        lo, hi = src.chunk_ids(inst.chunk)
        ids = np.arange(lo, hi, dtype=np.int64)
        seg, t = src.locate(ids)
        s_lo, s_hi = (int(x[0]) for x in src.chunk_steps(np.array([inst.chunk])))
        steps = np.arange(s_lo, s_hi)
        gseg = np.searchsorted(src.start, steps, side="right") - 1
        row_of_step = steps + src._off(gseg)  # dataset rows (frames for Atari)
        r_lo = int(row_of_step[0]) - (src.k - 1)
        local = row_of_step - r_lo  # ring offset of each step's row
        r0 = inst.row
        data: dict[str, np.ndarray] = {}
        for name, col in src.columns.items():
            if name.startswith("observation") and src.k > 1:  # frame rows, read as they lie
                _read(col, r_lo, inst.rows, self._ring[name][r0 : r0 + inst.rows])
                continue
            if name in self._ring and src.k == 1:  # step rows, read into the ring
                values = self._ring[name][r0 : r0 + s_hi - s_lo]
                _read(col, s_lo, s_hi - s_lo, values)
            else:  # step columns of frame-stacked data: at their steps' newest frames
                values = np.empty((s_hi - s_lo, *col.shape), col.dtype)
                _read(col, s_lo, s_hi - s_lo, values)
                if name in self._ring:
                    self._ring[name][r0 + local] = values
            data[name] = values
        if self.spec.return_to_go:
            assert src.cum_reward is not None  # built when spec.return_to_go
            c0 = src.cum_reward[inst.chunk]
            cum = np.cumsum(np.concatenate([[c0], data["reward"].astype(np.float64)]))[:-1]
            end = src.cum_end[gseg]
            self._ring["return_to_go"][r0 + local] = (end - cum).astype(np.float32)
        if self.spec.timestep:  # the step's index in its segment, as SequenceView gives it
            self._ring["timestep"][r0 + local] = steps - src.start[gseg]
        sl = slice(inst.slot, inst.slot + inst.n)
        slot = self._slot
        last = src.last[seg]
        slot["row"][sl] = r0 + local[t - s_lo]
        slot["source"][sl] = inst.source
        slot["index"][sl] = ids
        slot["epoch"][sl] = inst.epoch
        if self.spec.kind == "transition":
            sp = self.spec
            reward, discount, nxt = n_step_targets(
                data["reward"], data["discount"], t - s_lo, last - s_lo, sp.n_step, sp.gamma,
                sp.reward_clip,
            )  # fmt: skip
            slot["gap"][sl] = nxt - (t - s_lo)
            slot["reward"][sl] = reward
            slot["discount"][sl] = discount
        else:
            slot["valid"][sl] = np.minimum(self.spec.sequence_length, last - t + 1)

    # -- drawing -------------------------------------------------------------------------------
    def _fill(self, upto: float) -> None:
        """Plan (and start decoding) every chunk that starts before stream position ``upto``,
        and as many after it as the rings hold."""
        while self._plan["pos"] < upto:
            if self._next() is None:
                raise RuntimeError(
                    "stream sampler: the ring is full before the window is (a layout bug)"
                )
        while self._next() is not None:  # decode ahead as far as the rings hold
            pass

    def _bucket_draws(self, q: int) -> np.ndarray:
        """Slots of the draws whose times fall in bucket ``q``, in time order."""
        lo, hi = q * self.bucket, (q + 1) * self.bucket
        self._fill(hi)
        times, slots = [], []
        for inst in self._live:
            if inst.pos >= hi:
                break
            a = int(np.searchsorted(inst.times, lo, side="left"))
            b = int(np.searchsorted(inst.times, hi, side="left"))
            if b > a:
                inst.future.result()  # decoded (raises the decoder's error, e.g. a bad frame)
                times.append(inst.times[a:b])
                slots.append(inst.slot + inst.order[a:b])
        if not times:
            return np.zeros(0, np.int64)
        times_all, slots_all = np.concatenate(times), np.concatenate(slots)
        return slots_all[np.argsort(times_all, kind="stable")]

    def _release(self, q: int) -> None:
        """Free the oldest chunks whose draws all fall before bucket ``q``."""
        edge = q * self.bucket
        while self._live and self._live[0].times[-1] < edge:
            inst = self._live.popleft()
            inst.future.result()
            self._rows.free_oldest()
            self._slots.free_oldest()

    def sample_sourced(self) -> tuple[Transition | SequenceBatch, SampleSource]:
        """The next batch and where each of its samples came from."""
        if self._closed:
            raise RluError("the stream sampler is closed")
        parts, need = [], self.batch_size
        while need:
            if self._draws is None:
                self._release(self._bucket)
                self._draws = self._bucket_draws(self._bucket)
            take = self._draws[self._offset : self._offset + need]
            if len(take):  # gathered now: the next bucket may free what these draw from
                parts.append(self._gather(take))
            need -= len(take)
            self._offset += len(take)
            if self._offset >= len(self._draws):
                self._bucket, self._offset, self._draws = self._bucket + 1, 0, None
        if len(parts) == 1:
            return parts[0]
        first = parts[0][0]
        batch = type(first)(*(_concat([p[0][i] for p in parts]) for i in range(len(first))))
        source = SampleSource(*(np.concatenate([p[1][i] for p in parts]) for i in range(4)))
        return batch, source

    def sample(self) -> Transition | SequenceBatch:
        """The next batch (the agent's named tuple)."""
        return self.sample_sourced()[0]

    def __iter__(self) -> Iterator[Transition | SequenceBatch]:
        while True:
            yield self.sample()

    def _gather(self, slots: np.ndarray) -> tuple[Any, SampleSource]:
        s, ring, k = self._slot, self._ring, self.schema.frame_stack
        row = s["row"][slots]
        d = s["source"][slots]
        source = SampleSource(d, self._task_of[d], s["index"][slots], s["epoch"][slots])
        if self.spec.kind == "transition":
            gap = s["gap"][slots].astype(np.int64)
            nxt = row + gap
            if k > 1:
                obs, next_obs = _stacked_pair(ring["observation"], row, gap, k)
            else:
                obs, next_obs = self._obs(row), self._obs(nxt)
            action = np.take(ring["action"], row, axis=0)
            batch: Any = Transition(obs, action, s["reward"][slots], s["discount"][slots],
                                    next_obs, np.take(ring["action"], nxt, axis=0))  # fmt: skip
            return batch, source
        L = self.spec.sequence_length
        valid = s["valid"][slots]
        mask = np.arange(L) < valid[:, None]
        steps = row[:, None] + np.minimum(np.arange(L), (valid - 1)[:, None])

        def padded(x: np.ndarray) -> np.ndarray:
            m = mask.reshape(mask.shape + (1,) * (x.ndim - 2))
            return np.where(m, x, np.zeros((), x.dtype))

        if k > 1:
            frames = np.take(ring["observation"], steps[..., None] - (k - 1) + np.arange(k),
                             axis=0)  # fmt: skip
            obs = padded(np.moveaxis(frames, -3, -1))
        else:
            obs = self._obs(steps)
            obs = (
                {key: padded(v) for key, v in obs.items()} if isinstance(obs, dict) else padded(obs)
            )
        rtg = None
        if self.spec.return_to_go:
            rtg = np.where(mask, np.take(ring["return_to_go"], steps), np.float32(0))
        ts = None
        if self.spec.timestep:
            ts = np.where(mask, np.take(ring["timestep"], steps), 0)
        batch = SequenceBatch(
            observation=obs,
            action=padded(np.take(ring["action"], steps, axis=0)),
            reward=padded(np.take(ring["reward"], steps)),
            discount=padded(np.take(ring["discount"], steps)),
            is_first=padded(np.take(ring["is_first"], steps)),
            is_last=padded(np.take(ring["is_last"], steps)),
            mask=mask,
            return_to_go=rtg,
            timestep=ts,
        )
        return batch, source

    def _obs(self, rows: np.ndarray) -> Any:
        if isinstance(self.schema.observation, ArraySpec):
            return np.take(self._ring["observation"], rows, axis=0)
        return {k: np.take(self._ring[f"observation/{k}"], rows, axis=0)
                for k in self.schema.observation}  # fmt: skip

    # -- lifetime ------------------------------------------------------------------------------
    def _drain(self) -> None:
        for inst in getattr(self, "_live", ()):
            inst.future.cancel()
        for inst in getattr(self, "_live", ()):
            if not inst.future.cancelled():
                try:
                    inst.future.result()
                except Exception:  # noqa: BLE001 - a failed chunk no longer matters
                    pass

    def close(self) -> None:
        """Stop the decoding threads (the buffer is freed with the sampler)."""
        if not self._closed:
            self._closed = True
            self._drain()
            self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> StreamSampler:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_pool", None) is not None and not self._closed:
            self._closed = True
            self._pool.shutdown(wait=False, cancel_futures=True)


def _cores() -> int:
    from rlu.system import available_cores

    return available_cores()


def _concat(parts: list[Any]) -> Any:
    if parts[0] is None:
        return None
    if isinstance(parts[0], dict):
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return np.concatenate(parts)


def _stacked_pair(frames: np.ndarray, row: np.ndarray, gap: np.ndarray, k: int) -> tuple:
    """The stacks at ring rows ``row`` and ``row + gap`` (newest frames) from one gather of
    ``k + gap`` frames each (``DatasetView.stacked_pair``'s arithmetic and layout)."""
    first = row - (k - 1)
    span = k + int(gap.max(initial=1))
    rows = np.minimum(first[:, None] + np.arange(span), (first + gap + k - 1)[:, None])
    got = np.take(frames, rows, axis=0)
    current = got[:, :k]
    if int(gap.min(initial=1)) == int(gap.max(initial=1)):
        later = got[:, int(gap.max(initial=1)) :][:, :k]
    else:
        later = got[np.arange(len(gap))[:, None], gap[:, None] + np.arange(k)]
    return np.moveaxis(current, 1, -1), np.moveaxis(later, 1, -1)


def _read(col: _Column, row: int, n: int, out: np.ndarray) -> None:
    """Rows ``row .. row + n`` of a column into ``out`` (C-contiguous): one read of the file
    (and of the zlib offsets), the file opened for it and closed."""
    flags = os.O_RDONLY | os.O_CLOEXEC | getattr(os, "O_NOFOLLOW", 0)
    if col.zlib:
        offsets = np.empty(n + 1, "<i8")
        assert col.offsets is not None  # a zlib column's
        _pread_into(col.offsets, flags, row * 8, offsets, None)
        sizes = np.diff(offsets)
        if offsets[0] < 0 or offsets[-1] > col.size or (sizes < 8).any():
            raise FormatError(f"{col.offsets}: offsets of rows {row}..{row + n} changed since "
                              f"the dataset was opened; {_RECREATE}")  # fmt: skip
        lo = int(offsets[0])
        data = bytearray(int(offsets[-1]) - lo)
        _pread_into(col.path, flags, lo, np.frombuffer(data, np.uint8), col.size)
        frame = out.reshape(n, -1)
        bad = inflate_frames(data, offsets[:-1] - lo, offsets[1:] - lo, frame, frame[0].nbytes)
        if bad is not None:
            j, why = bad
            raise FormatError(
                f"{col.path}: frame {row + j} is not a zlib stream of one {frame[0].nbytes}-byte "
                f"frame ({why}); {_RECREATE}"
            )
        return
    item = out[0].nbytes if n else 0
    _pread_into(col.path, flags, row * item, out, col.size)


def _pread_into(path: Path, flags: int, at: int, out: np.ndarray, size: int | None) -> None:
    try:
        fd = os.open(path, flags)
    except OSError as e:
        raise FormatError(f"{path}: cannot be read ({e.strerror}); {_RECREATE}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or (size is not None and st.st_size != size):
            raise FormatError(f"{path}: changed since the dataset was opened; {_RECREATE}")
        want = out.nbytes
        got = os.preadv(fd, [out.data.cast("B")], at) if want else 0
        if got != want:
            raise FormatError(f"{path}: {want} bytes at offset {at} hold {got}; {_RECREATE}")
    finally:
        os.close(fd)


def stream_sampler(
    datasets: str | os.PathLike | Dataset | Sequence[str | os.PathLike | Dataset],
    batch_size: int,
    seed: int = 0,
    weights: Sequence[float] | None = None,
    kind: str = "transition",
    length: int | None = None,
    memory: int = DEFAULT_MEMORY,
    n_step: int = 1,
    gamma: float = 1.0,
    reward_clip: float | None = None,
    return_to_go: bool = False,
    timestep: bool = False,
    reuse: int = DEFAULT_REUSE,
    workers: int | None = None,
) -> StreamSampler:
    """A :class:`StreamSampler` of ``batch_size`` transitions (``kind="transition"``, n-step
    and reward clipping as :class:`rlu.types.BatchSpec` says) or windows of ``length`` steps
    (``kind="sequence"``) from ``datasets``, in ``memory`` bytes of decoded rows."""
    if kind == "sequence" and length is None:
        raise RluError("kind='sequence' needs length (the window's steps)")
    spec = BatchSpec(batch_size, kind, n_step, gamma, length or 1, reward_clip,
                     return_to_go=return_to_go, timestep=timestep)  # fmt: skip
    return StreamSampler(datasets, spec, seed, weights, memory, reuse, workers)
