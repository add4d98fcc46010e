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

    def __init__(
        self,
        path: str,
        batch_size: int,
        seed: int = 0,
        kind: str = "transition",
        n_step: int = 1,
        gamma: float = 1.0,
        sequence_length: int = 1,
        stride: int = 1,
    ):
        super().__init__()
        self.path, self.batch_size, self.seed, self.kind = str(path), batch_size, seed, kind
        self.n_step, self.gamma = n_step, gamma
        self.sequence_length, self.stride = sequence_length, stride

    def _sampler(self) -> Sampler:
        info = torch.utils.data.get_worker_info()
        seed = self.seed + (info.id if info is not None else 0)
        return make_sampler(
            self.path,
            self.batch_size,
            seed,
            self.kind,
            self.n_step,
            self.gamma,
            self.sequence_length,
            self.stride,
        )

    def __iter__(self):
        sampler = self._sampler()
        while True:
            yield to_torch(sampler.sample())
