"""The data layer: the episode store, its views and samplers, the original release, interop.

Imports numpy only; PyTorch / JAX adapters and the release reader load when used.
"""

from __future__ import annotations

import os
from typing import Any

from rlu.data.episode import Segment, make_episode
from rlu.data.store import Dataset, DatasetWriter, Schema, open_dataset
from rlu.data.stream import SampleSource, StreamSampler, stream_sampler
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
    "SampleSource",
    "Sampler",
    "Schema",
    "Segment",
    "SequenceView",
    "StreamSampler",
    "TransitionView",
    "load_dataset",
    "make_episode",
    "make_sampler",
    "make_view",
    "open_dataset",
    "sequence_sampler",
    "stream_sampler",
    "transition_sampler",
]


def load_dataset(name: str | os.PathLike, source: str = "auto", **kwargs: Any) -> Dataset:
    """Open a dataset in one line, by task or by folder.

        ds = rlu.load_dataset("control_suite/cartpole_swingup")   # the dataset rlu ships
        ds = rlu.load_dataset("rlu_atari/Pong_run_1")             # TFDS names work too
        ds = rlu.load_dataset("runs/my_data")                     # a folder rlu wrote

    ``source="auto"`` (the default) opens a dataset folder, or for a task id (or TFDS name) what
    is on this machine without the network: the dataset rlu ships for the task (unless the name
    or ``family`` / ``run`` / ``challenge`` / ``size`` / ``shards`` pick a release dataset), the
    release dataset converted in the cache (``$RLU_CACHE_DIR``), or its shards downloaded there
    (converted on this call); else an RluError names the ``rlu download`` command that fetches
    them. ``source="release"`` downloads and converts on first use (``rlu.data.release``);
    ``source="local"`` takes a folder only.
    """
    if source == "local" or not isinstance(name, str) or os.path.exists(name):
        return open_dataset(name, **kwargs)
    if source == "auto":
        from rlu.data.release.load import load_task_dataset
        from rlu.tasks import DOMAINS, resolve_task
        from rlu.types import RluError

        try:
            resolve_task(name)
        except RluError as e:
            if name.split("/")[0] in DOMAINS or name.startswith("rlu_"):
                raise
            raise RluError(f"{name}: no such dataset folder, and {e}") from None
        return load_task_dataset(name, **kwargs)
    if source == "release":
        from rlu.data.release.load import load_release_dataset

        return load_release_dataset(name, **kwargs)
    from rlu.types import RluError

    raise RluError(f"unknown dataset source {source!r}; use 'auto', 'local' or 'release'")
