"""``rlu.load_dataset(task, source="release")``: download and convert on first use, reuse after.

The converted dataset lives at ``CACHE/datasets/<task>/<family>[/<dataset>][/shards-<sel>]``; a
second call opens it without touching the network (the download manifest is only consulted when
the dataset is missing).

``load_task_dataset`` is ``rlu.load_dataset(task)`` (``source="auto"``): what is already on this
machine, never the network. The shipped dataset where one ships and the name picks no release
dataset; else the converted release dataset in the cache; else its shards, downloaded into the
cache earlier (``rlu download``), converted now; else an error naming the ``rlu download``
command that fetches them.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
from collections.abc import Sequence
from typing import Any

from rlu.data.release import catalog
from rlu.data.release.convert import convert
from rlu.data.release.download import cache_root, download, read_manifest, release_dir
from rlu.data.store import Dataset, open_dataset
from rlu.files import open_private
from rlu.types import RluError

# Keywords of load_release_dataset that pick a release dataset (so not the shipped one).
_PICKS = ("family", "run", "challenge", "size", "shards")


def release_dataset_path(
    selection: catalog.ReleaseSelection, cache_dir: str | os.PathLike | None, all_shards: bool
) -> str:
    parts = [cache_root(cache_dir), "datasets", *selection.task.id.split("/"), selection.family]
    if selection.binding:
        parts.extend(selection.binding.split("/"))
    if not all_shards:
        names = "\n".join(selection.objects).encode()
        parts.append(f"shards-{len(selection.objects)}-{hashlib.sha256(names).hexdigest()[:10]}")
    return os.path.join(*parts)


def load_release_dataset(
    task_id: str,
    family: str | None = None,
    run: str | int | None = None,
    challenge: str | None = None,
    size: str | None = None,
    cache_dir: str | os.PathLike | None = None,
    base_url: str | None = None,
    shards: str | Sequence[int] | None = None,
    workers: int | None = None,
    progress: bool | None = None,
) -> Dataset:
    """The converted release dataset of ``task_id`` (downloaded and converted on first use).

    ``progress``: False shows nothing; otherwise download and conversion show an
    :class:`rlu.progress.Progress` on stderr (a bar on a terminal, a line every 10 s elsewhere).
    A download that cannot succeed (offline, a refused port, HTTP 403/404) raises at once.
    """
    sel = catalog.select(task_id, family, run, challenge, size, shards)
    dest = release_dataset_path(sel, cache_dir, all_shards=shards is None)
    if os.path.isfile(os.path.join(dest, "manifest.json")):
        return open_dataset(dest)
    os.makedirs(os.path.dirname(dest), exist_ok=True)
    # never through a planted link (open_private refuses one)
    fd = open_private(dest + ".lock", os.O_RDWR | os.O_CREAT, "dataset lock")
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # two processes loading one dataset: one converts
        if os.path.isfile(os.path.join(dest, "manifest.json")):
            return open_dataset(dest)
        _fetch_and_convert(sel, dest, cache_dir, base_url, workers, progress)
    finally:
        os.close(fd)
    return open_dataset(dest)


def _fetch_and_convert(sel, dest, cache_dir, base_url, workers, progress) -> None:
    fetched = download(sel.objects, cache_dir=cache_dir, base_url=base_url, progress=progress)
    convert(
        [f.path for f in fetched],
        sel.family,
        sel.task.id,
        dest,
        challenge=sel.binding.split("/")[0] if sel.task.domain == "rwrl" else None,
        run=sel.binding if sel.task.domain == "atari" else None,
        workers=workers,
        progress=progress is not False,
        provenance={
            "dataset": sel.binding,
            "objects": list(sel.objects),
            "sha256": {f.object: f.sha256 for f in fetched},
        },
    )


def load_task_dataset(name: str, **kwargs: Any) -> Dataset:
    """``rlu.load_dataset(name)`` for a task id or TFDS name: see the module docstring.

    ``kwargs`` are ``load_release_dataset``'s; ``verify=True`` checks every sha256 of a dataset
    opened as it is.
    """
    from rlu.data.bundled import bundled_dataset_path, bundled_tasks
    from rlu.tasks import resolve_task

    verify = bool(kwargs.pop("verify", False))
    ref = resolve_task(name)
    task = ref.task
    picked = ref.family is not None or any(kwargs.get(k) is not None for k in _PICKS)
    shipped = bundled_dataset_path(task.id)
    if shipped is not None and not picked:
        return open_dataset(shipped, verify=verify)
    family, run, challenge, size = ref.dataset_settings(
        kwargs.pop("family", None),
        kwargs.pop("run", None),
        kwargs.pop("challenge", None),
        kwargs.pop("size", None),
    )
    shards = kwargs.get("shards")
    sel = catalog.select(task.id, family, run, challenge, size, shards)
    cache_dir = kwargs.get("cache_dir")
    dest = release_dataset_path(sel, cache_dir, all_shards=shards is None)
    if os.path.isfile(os.path.join(dest, "manifest.json")):
        return open_dataset(dest, verify=verify)
    if _downloaded(sel, cache_dir):
        kw = {k: v for k, v in kwargs.items() if k != "base_url"}
        return load_release_dataset(task.id, sel.family, run, challenge, size, **kw)
    if shipped is not None:
        ships = f"the {task.id} dataset rlu ships is rlu-generated, not this release dataset"
    else:
        ships = f"rlu ships {', '.join(bundled_tasks()) or 'no dataset'} only"
    what = f"{sel.family} {sel.binding}".strip()
    raise RluError(
        f"no {task.id} release dataset ({what}) on this machine: {ships}, and the cache "
        f"{cache_root(cache_dir)} holds neither it converted nor its {len(sel.objects)} shards; "
        f"fetch them with `{download_command(sel, shards, cache_dir)}`, then this call converts "
        "them without the network (or pass source='release' to download and convert in one go)"
    )


def download_command(
    sel: catalog.ReleaseSelection,
    shards: str | Sequence[int] | None = None,
    cache_dir: str | os.PathLike | None = None,
) -> str:
    """The ``rlu download`` command line that fetches the shards of ``sel``."""
    parts = ["rlu download", sel.task.id]
    if sel.family != sel.task.release[0].family:
        parts += ["--family", sel.family]
    if sel.task.domain == "atari":
        parts += ["--run", sel.binding.removeprefix("run_")]
    elif sel.task.domain == "rwrl":
        challenge, size = sel.binding.split("/")
        parts += ["--challenge", challenge, "--size", size]
    if shards is not None:
        spec = shards if isinstance(shards, str) else ",".join(str(i) for i in shards)
        parts += ["--shards", spec]
    if cache_dir is not None:
        parts += ["--cache-dir", os.fspath(cache_dir)]
    return " ".join(parts)


def _downloaded(sel: catalog.ReleaseSelection, cache_dir: str | os.PathLike | None) -> bool:
    """Whether every shard of ``sel`` was downloaded into the cache (file and manifest entry;
    the download step verifies them again before they are used)."""
    root = release_dir(cache_dir)
    entries = read_manifest(root)  # never through a planted link
    return all(
        o in entries and os.path.isfile(os.path.join(root, *o.split("/"))) for o in sel.objects
    )
