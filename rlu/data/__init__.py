"""The data layer: the episode store, its views and samplers, the original release, interop.

Imports numpy only; PyTorch / JAX adapters and the release reader load when used.
"""

from __future__ import annotations

from typing import Any

from rlu.data.episode import Segment, make_episode
from rlu.data.store import Dataset, DatasetWriter, Schema, open_dataset
from rlu.data.views import (
    Sampler,
    SequenceView,
    TransitionView,
    make_sampler,
    make_view,
    sequence_sampler,
    transition_sampler,
)

__all__ = [
    "Dataset",
    "DatasetWriter",
    "Sampler",
    "Schema",
    "Segment",
    "SequenceView",
    "TransitionView",
    "load_dataset",
    "make_episode",
    "make_sampler",
    "make_view",
    "open_dataset",
    "sequence_sampler",
    "transition_sampler",
]


def load_dataset(task_or_path: str, source: str = "local", **kwargs: Any) -> Dataset:
    """Open a dataset: a directory written by rlu (``source="local"``, the default).

    ``source="release"`` downloads and converts the original release on first use (see
    ``rlu.data.release``).
    """
    if source == "local":
        return open_dataset(task_or_path, **kwargs)
    if source == "release":
        from rlu.data.release.load import load_release_dataset

        return load_release_dataset(task_or_path, **kwargs)
    from rlu.types import RluError

    raise RluError(f"unknown dataset source {source!r}; use 'local' or 'release'")
