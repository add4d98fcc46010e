"""PyTorch adapter: batches as tensors, and a DataLoader-compatible iterable dataset.

Imports torch only when this module is used. ``TorchSampler`` re-opens the dataset in each worker
process (only the path crosses the process boundary). Its batch streams are spawned from one
``numpy.random.SeedSequence`` per run seed (``rlu.types.seed_stream``), one child per (worker,
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

from typing import Any

import numpy as np
import torch

from rlu.data.views import Sampler, make_sampler
from rlu.types import BatchSpec, seed_stream


def to_torch(batch: Any, device: str | torch.device = "cpu") -> Any:
    """A named batch (Transition / Sequence) of numpy arrays as the same type of tensors."""

    def conv(x: Any) -> Any:
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

    def __iter__(self):
        sampler = self._sampler()
        while True:
            yield to_torch(sampler.sample())
