"""The data layer: the episode store, its views and samplers, the original release, interop.

Imports numpy only; PyTorch / JAX adapters and the release reader load when used.
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Sequence
from typing import Any

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
from rlu.segments import Segment, make_episode

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

SOURCES = ("auto", "local", "release")
"""What ``load_dataset``'s ``source`` may be."""

_RELEASE_KEYWORDS = ("family", "run", "challenge", "size", "shards", "cache_dir", "workers")


def load_dataset(
    name: str | os.PathLike,
    source: str = "auto",
    *,
    family: str | None = None,
    run: str | int | None = None,
    challenge: str | None = None,
    size: str | None = None,
    shards: str | Sequence[int] | None = None,
    cache_dir: str | os.PathLike | None = None,
    base_url: str | None = None,
    workers: int | None = None,
    progress: bool | None = None,
    verify: bool = False,
    **unknown: Any,
) -> Dataset:
    """Open a dataset in one line, by task, by TFDS name or by folder: the one resolver of every
    dataset name rlu takes (``rlu train --dataset``, ``rlu sweep``, config files, Python).

        ds = rlu.load_dataset("control_suite/cartpole_swingup")   # the dataset rlu ships
        ds = rlu.load_dataset("rlu_atari/Pong_run_1")             # TFDS names work too
        ds = rlu.load_dataset("runs/my_data")                     # a folder rlu wrote

    ``source="auto"`` (the default) opens a dataset folder, or for a task id (or TFDS name) what
    is on this machine without the network: the dataset rlu ships for the task (unless the name
    or ``family`` / ``run`` / ``challenge`` / ``size`` / ``shards`` pick a release dataset), the
    release dataset converted in the cache (``cache_dir``, default ``$RLU_CACHE_DIR`` or
    ``~/.cache/rlu``), or its shards downloaded there (converted on this call, with ``workers``
    processes and ``progress`` shown); else an RluError names what was tried and the
    ``rlu download`` command that fetches them. ``source="release"`` downloads (from
    ``base_url``, default the public bucket) and converts on first use (``rlu.data.release``);
    ``source="local"`` takes a folder only. ``verify=True`` checks every file's sha256.

    A name that is an existing path is a folder. A cache entry is used only if it holds a
    dataset of the task asked for and lies inside the cache (no symbolic link on the way); a
    keyword this function does not take is refused, naming the closest one.
    """
    if unknown:
        raise _unknown_keyword(next(iter(unknown)))
    if source not in SOURCES:
        from rlu.types import RluError

        raise RluError(f"unknown dataset source {source!r}; use 'auto', 'local' or 'release'")
    release: dict[str, Any] = {  # keyword arguments of the loaders, each typed there
        "family": family,
        "run": run,
        "challenge": challenge,
        "size": size,
        "shards": shards,
        "cache_dir": cache_dir,
        "workers": workers,
    }
    if source == "local" or not isinstance(name, str) or os.path.exists(name):
        _only_folder_keywords(name, release, base_url)
        return open_dataset(name, verify=verify)
    if source == "auto":
        return _on_this_machine(name, base_url, verify, progress, release)
    from rlu.data.release.load import load_release_dataset

    ds = load_release_dataset(name, base_url=base_url, progress=progress, **release)
    if verify:
        return open_dataset(ds.path, verify=True)
    return ds


def _on_this_machine(
    name: str, base_url: str | None, verify: bool, progress: bool | None, release: dict[str, Any]
) -> Dataset:
    """``load_dataset``'s ``source="auto"`` for a name that is no folder: a task id or TFDS
    name, opened from what this machine holds (``rlu.data.release.load.load_task_dataset``)."""
    from rlu.data.release.load import load_task_dataset
    from rlu.tasks import resolve_task
    from rlu.types import RluError

    try:
        resolve_task(name)
    except RluError as e:
        folder = f"dataset {name!r}: no such folder ({os.path.abspath(name)})"
        if _looks_like_a_path(name):
            raise RluError(
                f"{folder}; check the path (a task id or TFDS name reads like "
                "control_suite/cartpole_swingup or rlu_atari/Pong_run_1: `rlu list`)"
            ) from None
        raise RluError(f"{folder}, and not a task id or TFDS name: {e}") from None
    if base_url is not None:
        raise RluError(
            "base_url applies to source='release' (download and convert); the default "
            "source reads what is on this machine only"
        )
    return load_task_dataset(name, verify=verify, progress=progress, **release)


def _looks_like_a_path(name: str) -> bool:
    """A name no task id reads like: absolute, relative to ``.`` / ``~``, or deeper than
    ``builder/config`` whose first part is no domain or TFDS builder."""
    from rlu.tasks import DOMAINS, TFDS_BUILDERS

    if name.startswith(("/", ".", "~")) or os.sep + os.sep in name:
        return True
    first = name.split("/")[0]
    return (
        "/" in name
        and first not in DOMAINS
        and first not in TFDS_BUILDERS
        and not (first.startswith("rlu_"))
    )


def _unknown_keyword(key: str) -> Exception:
    from rlu.types import RluError

    known = [*_RELEASE_KEYWORDS, "source", "base_url", "progress", "verify"]
    close = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]!r}?" if close else "."
    return RluError(
        f"load_dataset() takes no keyword {key!r}{hint} It takes {', '.join(sorted(known))}"
    )


def _only_folder_keywords(
    name: str | os.PathLike, release: dict[str, Any], base_url: str | None
) -> None:
    """A folder is one dataset: the keywords that pick a release dataset do not apply."""
    given = [k for k, v in release.items() if v is not None]
    if base_url is not None:
        given.append("base_url")
    if given:
        from rlu.types import RluError

        raise RluError(
            f"{name}: a dataset folder is one dataset, and {', '.join(given)} pick a release "
            "dataset of a task; drop them, or name the task id instead of the folder"
        )
