"""PyTorch adapter: batches as tensors, a DataLoader-compatible iterable dataset, and the training
loop's data path on an accelerator (``device_batch``, ``Prefetcher``, ``DeviceSampler``).

Imports torch only when this module is used. ``TorchSampler`` re-opens the dataset in each worker
process (only the path crosses the process boundary). Its batch streams are spawned from one
``numpy.random.SeedSequence`` per run seed (``rlu.seeds.seed_stream``), one child per (worker,
pass over the loader), so no two (run seed, worker, pass) streams coincide: with ``seed + k``
run 0's worker 1 replayed run 1's worker 0, and iterating the same loader again replayed it.

- ``num_workers=0``: the stream of pass ``e`` is ``seed_stream(seed, 0, e)``, ``e`` counting the
  ``iter()`` calls on this object.
- worker ``k`` of ``N``: ``seed_stream(seed, 1 + k, b)`` where ``b`` is the loader's per-pass base
  seed (``get_worker_info().seed - k``). The loader draws ``b`` afresh for every pass from its
  ``generator`` (or torch's global generator), so a pass is reproducible when that generator is
  seeded, as for any DataLoader shuffle: ``DataLoader(..., generator=torch.Generator()
  .manual_seed(0))``. Worker processes are new on every pass (unless persistent), so a count of
  passes kept in a worker would restart at 0; the base seed is what tells passes apart.
"""

from __future__ import annotations

import contextlib
import os
import queue
import threading
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
import torch

from rlu.data.store import Dataset, open_dataset
from rlu.data.views import Sampler, TransitionView, make_sampler
from rlu.seeds import seed_stream
from rlu.types import ArraySpec, BatchSpec, RluError, Transition


def to_torch(batch: Any, device: str | torch.device = "cpu") -> Any:
    """A named batch (Transition / Sequence) of numpy arrays as the same type of tensors."""

    def conv(x: Any) -> Any:
        if x is None:
            return None
        if isinstance(x, dict):
            return {k: conv(v) for k, v in x.items()}
        return torch.from_numpy(np.ascontiguousarray(x)).to(device)

    return type(batch)(*(conv(x) for x in batch))


class TorchSampler(torch.utils.data.IterableDataset):
    """Endless uniform batches from a stored dataset, as tensors (``batch_size=None`` in the
    loader)."""

    def __init__(self, path: str, spec: BatchSpec, seed: int = 0):
        super().__init__()
        self.path, self.spec, self.seed = str(path), spec, seed
        self._passes = 0  # iter() calls in this process (the stream key without workers)
        seed_stream(seed)  # a bad seed fails here, not in a worker process

    def stream_key(self) -> tuple[int, int]:
        """The (lane, pass) key of the next ``iter()`` in this process (see the module doc)."""
        info = torch.utils.data.get_worker_info()
        if info is None:
            return 0, self._passes
        return 1 + info.id, (info.seed - info.id) % 2**64

    def _sampler(self) -> Sampler:
        lane, epoch = self.stream_key()
        self._passes += 1
        sampler = make_sampler(self.path, self.spec, 0)
        stream = np.random.default_rng(seed_stream(self.seed, lane, epoch))
        sampler.set_state({"bit_generator": stream.bit_generator.state})
        return sampler

    def __iter__(self) -> Iterator[Any]:
        sampler = self._sampler()
        while True:
            yield to_torch(sampler.sample())


# --- the training loop's data path on an accelerator ----------------------------------------
# docs/devices.md: on CUDA the loop's batches are sampled on the host by a background thread
# and copied from pinned memory on a side stream while the learner runs (``Prefetcher``), or
# gathered on the device from columns held there (``DeviceSampler``). Either gives the batches
# of ``rlu.data.views.Sampler`` with the same seed, in the same order.


def device_batch(batch: Any, device: torch.device) -> Any:
    """A named batch of numpy arrays as tensors on ``device``: float64 becomes float32 (the
    agents' rule), other dtypes and the strides stay (a frame stack stays a view of frame-major
    memory: no transpose on the host), tensors already on ``device`` pass through. On CUDA the
    host side is pinned and the copy asynchronous on the current stream."""
    cuda = device.type == "cuda"

    def conv(x: Any) -> Any:
        if x is None:
            return None
        if isinstance(x, Mapping):
            return {k: conv(v) for k, v in x.items()}
        if isinstance(x, torch.Tensor):
            return x if x.device == device else x.to(device, non_blocking=cuda)
        a = np.asarray(x)
        if a.dtype == np.float64:
            a = a.astype(np.float32)
        elif not a.flags.writeable or any(st < 0 for st in a.strides):
            a = a.copy()
        t = torch.from_numpy(a)
        if device.type == "cpu":
            return t
        return (t.pin_memory() if cuda else t).to(device, non_blocking=cuda)

    return type(batch)(*(conv(x) for x in batch))


def _tensors(x: Any) -> Iterator[torch.Tensor]:
    for v in x:
        if isinstance(v, Mapping):
            yield from (t for t in v.values() if isinstance(t, torch.Tensor))
        elif isinstance(v, torch.Tensor):
            yield v


class _Failed:
    def __init__(self, error: BaseException):
        self.error = error


class Prefetcher:
    """A sampler's batches, made up to ``depth`` ahead of the learner by a background thread:
    the thread samples (numpy releases the GIL in its gathers) and, on CUDA, copies each batch
    from pinned memory on a side stream; ``sample()`` makes the learner's stream wait for that
    copy only. The batches and their order are the sampler's own; ``get_state()`` is the
    sampler's state after the last batch handed out (what a checkpoint must hold: the thread
    has already drawn further). On the CPU the batches stay as the sampler makes them. An
    error in the thread is raised by the ``sample()`` that would have returned its batch."""

    def __init__(self, sampler: Any, device: torch.device | str, depth: int = 2):
        if depth < 1:
            raise RluError(f"prefetch depth {depth}; use 1 or more (0: no prefetcher)")
        self.sampler, self.device = sampler, torch.device(device)
        self._state = sampler.get_state()
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._stream = torch.cuda.Stream(self.device) if self.device.type == "cuda" else None
        self._thread = threading.Thread(target=self._work, name="rlu-prefetch", daemon=True)
        self._thread.start()

    def _put(self, item: Any) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)  # wakes up to notice close()
                return True
            except queue.Full:
                continue
        return False

    def _work(self) -> None:
        try:
            while not self._stop.is_set():
                batch = self.sampler.sample()
                state = self.sampler.get_state()
                event = None
                if self._stream is not None:
                    with torch.cuda.stream(self._stream):
                        batch = device_batch(batch, self.device)
                        event = self._stream.record_event()
                if not self._put((batch, event, state)):
                    return
        except BaseException as error:  # handed to the learner's thread and raised there
            self._put(_Failed(error))

    def sample(self) -> Any:
        item = self._queue.get()
        if isinstance(item, _Failed):
            self.close()
            raise item.error
        batch, event, state = item
        if event is not None:
            stream = torch.cuda.current_stream(self.device)
            stream.wait_event(event)
            for t in _tensors(batch):  # made on the side stream, used on the learner's
                t.record_stream(stream)
        self._state = state
        return batch

    def get_state(self) -> dict:
        return self._state

    def close(self) -> None:
        self._stop.set()
        while self._thread.is_alive():
            with contextlib.suppress(queue.Empty):
                while True:
                    self._queue.get_nowait()
            self._thread.join(timeout=0.1)

    def __enter__(self) -> Prefetcher:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


@contextlib.contextmanager
def prefetched(sampler: Any, device: torch.device | str, depth: int) -> Iterator[Any]:
    """``sampler`` itself (``depth`` 0: sampled in line) or a :class:`Prefetcher` over it,
    closed on exit."""
    if depth <= 0:
        yield sampler
        return
    with Prefetcher(sampler, device, depth) as source:
        yield source


class _RowsView(TransitionView):
    """A :class:`TransitionView` whose observations are the store rows they are gathered from
    (frame rows ``(..., stack)`` for Atari, step rows otherwise): everything else in the batch
    is the view's own arithmetic, so ``DeviceSampler`` gathers exactly the view's frames."""

    def observation(self, seg: np.ndarray, steps: np.ndarray) -> Any:
        if self.schema.frame_stack > 1:
            first = self.frame_start[seg] + (steps - self.start[seg])  # frame row of step - k + 1
            return first[..., None] + np.arange(self.schema.frame_stack)
        if isinstance(self.schema.observation, ArraySpec):
            return np.asarray(steps)
        return {key: np.asarray(steps) for key in self.schema.observation}

    def stacked_pair(self, seg: np.ndarray, steps: np.ndarray, next_steps: np.ndarray) -> Any:
        return self.observation(seg, steps), self.observation(seg, next_steps)


DEVICE_MEMORY_SHARE = 0.8
"""The share of the device's free memory a dataset may take (the rest: networks, activations,
optimiser states, the batches in flight)."""


def _free_bytes(device: torch.device) -> int | None:
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    if device.type == "cpu":
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    return None


class DeviceSampler:
    """Uniform transition batches gathered on ``device`` from the dataset's observation columns
    held there (``rlu train --data-on-device``): Atari frames stay uint8, stored once, and are
    stacked by index on the device (a 1M-step Atari run is ~7 GB). The indices, rewards,
    discounts and actions are computed on the host by the store's own ``TransitionView``
    arithmetic from the same draws as ``rlu.data.views.Sampler`` with the same seed, so the
    batches are that sampler's, as tensors on ``device``. Sequence batches are not supported:
    their agents use the prefetcher."""

    def __init__(
        self, dataset: Any, spec: BatchSpec, seed: int = 0, device: torch.device | str = "cpu"
    ):
        ds: Dataset = dataset if isinstance(dataset, Dataset) else open_dataset(dataset)
        if spec.kind != "transition":
            raise RluError(
                f"--data-on-device gathers transition batches; this agent trains on "
                f"{spec.kind} batches. Drop --data-on-device (its batches are prefetched)"
            )
        self.view = _RowsView(ds, spec.n_step, spec.gamma, spec.reward_clip)
        if len(self.view) == 0:
            raise RluError(f"{ds.path}: the dataset has no TransitionView samples")
        self.batch_size, self.device = spec.batch_size, torch.device(device)
        self.rng = np.random.default_rng(seed)
        obs = ds.schema.observation
        keys = [""] if ds.schema.frame_stack > 1 or isinstance(obs, ArraySpec) else list(obs)
        names = {k: f"observation/{k}" if k else "observation" for k in keys}
        need = sum(int(np.prod(ds.column(n).shape)) * ds.column(n).dtype.itemsize
                   for n in names.values())  # fmt: skip
        free = _free_bytes(self.device)
        if free is not None and need > DEVICE_MEMORY_SHARE * free:
            raise RluError(
                f"{ds.path}: its observations take {need / 2**30:.2f} GiB, more than "
                f"{DEVICE_MEMORY_SHARE:.0%} of the {free / 2**30:.2f} GiB free on "
                f"{self.device}; drop --data-on-device (batches then come from the host, "
                "prefetched) or use a device with more memory"
            )
        self.columns = {k: self._upload(ds, name) for k, name in names.items()}
        if self.device.type == "cuda":  # uploads from pageable memory may still be in flight
            torch.cuda.synchronize(self.device)

    def _upload(self, ds: Dataset, name: str, chunk_bytes: int = 256 << 20) -> torch.Tensor:
        """A whole column on the device, decoded and copied in chunks (the host never holds
        more than one chunk; zlib image columns are decoded here, once)."""
        column = ds.column(name)
        shape, dtype = tuple(column.shape), np.dtype(column.dtype)
        out = torch.empty(shape, dtype=torch.from_numpy(np.zeros(0, dtype)).dtype,
                          device=self.device)  # fmt: skip
        rows = max(1, chunk_bytes // max(1, int(np.prod(shape[1:])) * dtype.itemsize))
        for start in range(0, shape[0], rows):
            part = np.array(column[start : start + rows])  # a writable copy of the chunk
            out[start : start + len(part)].copy_(torch.from_numpy(part))
        ds.release_pages(name, min_bytes=0)
        return out

    def _gather(self, rows: Any) -> Any:
        def take(key: str, index: np.ndarray) -> torch.Tensor:
            at = torch.from_numpy(index)
            if self.device.type == "cuda":
                at = at.pin_memory().to(self.device, non_blocking=True)
            return self.columns[key][at]

        if isinstance(rows, Mapping):
            return {k: take(k, r) for k, r in rows.items()}
        out = take("", rows)
        if self.view.schema.frame_stack > 1:  # (B, stack, H, W) -> (B, H, W, stack), a view
            out = out.movedim(-3, -1)
        return out

    def sample(self) -> Transition:
        ids = self.rng.integers(0, len(self.view), size=self.batch_size)  # Sampler's draws
        b = self.view.batch(ids)
        # the observations are gathered on the device below; None holds their places here
        batch = Transition(None, b.action, b.reward, b.discount, None, b.next_action)  # type: ignore[arg-type]
        rest = device_batch(batch, self.device)
        return rest._replace(
            observation=self._gather(b.observation),
            next_observation=self._gather(b.next_observation),
        )

    def get_state(self) -> dict:
        return {"bit_generator": self.rng.bit_generator.state}

    def set_state(self, state: dict) -> None:
        self.rng.bit_generator.state = state["bit_generator"]
