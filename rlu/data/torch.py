"""PyTorch adapter: batches as tensors, and a DataLoader-compatible iterable dataset.

Imports torch only when this module is used. ``TorchSampler`` re-opens the dataset in each worker
process (only the path crosses the process boundary) and gives worker ``k`` the seed
``seed + k``, so that ``DataLoader(TorchSampler(...), batch_size=None, num_workers=N)`` yields
independent, reproducible batch streams.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from rlu.data.views import Sampler, make_sampler
from rlu.types import BatchSpec


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

    def _sampler(self) -> Sampler:
        info = torch.utils.data.get_worker_info()
        seed = self.seed + (info.id if info is not None else 0)
        return make_sampler(self.path, self.spec, seed)

    def __iter__(self):
        sampler = self._sampler()
        while True:
            yield to_torch(sampler.sample())
