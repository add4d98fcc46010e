"""JAX adapter: batches as device arrays, with optional background prefetch.

Imports jax only when this module is used (``pip install 'rlu[jax]'``). A named batch
(``Transition`` / ``Sequence``) is a pytree, so ``to_jax`` keeps its type and field names.

``JaxBatches`` draws from the same seeded ``Sampler`` as the numpy path, so the stream of batches
is identical with or without prefetch; with ``prefetch=k > 0`` a background thread samples and
transfers up to ``k`` batches ahead of the training loop (numpy gathering and the host-to-device
copy overlap the jitted update). Use it as a context manager, or call ``close()``, to stop the
thread.
"""

from __future__ import annotations

import queue
import threading
from typing import Any

import jax
import numpy as np

from rlu.data.store import Dataset
from rlu.data.views import make_sampler
from rlu.types import BatchSpec, RluError


def to_jax(batch: Any, device: Any = None) -> Any:
    """A named batch of numpy arrays as the same named batch of jax arrays on ``device``."""
    host = jax.tree_util.tree_map(np.ascontiguousarray, batch)
    return jax.device_put(host, device)


class _Failed:
    def __init__(self, error: BaseException):
        self.error = error


class JaxBatches:
    """Endless uniform batches from a stored dataset as jax arrays (see the module docstring)."""

    def __init__(
        self,
        dataset: str | Dataset,
        spec: BatchSpec,
        seed: int = 0,
        prefetch: int = 2,
        device: Any = None,
    ):
        if prefetch < 0:
            raise RluError(f"JaxBatches prefetch={prefetch}; use 0 (none) or more")
        self.sampler = make_sampler(dataset, spec, seed)
        self.device, self.prefetch = device, int(prefetch)
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def _produce(self) -> None:
        assert self._queue is not None
        try:
            while not self._stop.is_set():
                item = to_jax(self.sampler.sample(), self.device)
                while not self._stop.is_set():
                    try:
                        self._queue.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
        except BaseException as e:  # handed to the consumer, raised there
            self._queue.put(_Failed(e))

    def __iter__(self) -> JaxBatches:
        return self

    def __next__(self) -> Any:
        if self.prefetch == 0:
            return to_jax(self.sampler.sample(), self.device)
        if self._thread is None:
            self._queue = queue.Queue(maxsize=self.prefetch)
            self._thread = threading.Thread(target=self._produce, daemon=True)
            self._thread.start()
        assert self._queue is not None
        item = self._queue.get()
        if isinstance(item, _Failed):
            raise item.error
        return item

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def __enter__(self) -> JaxBatches:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
