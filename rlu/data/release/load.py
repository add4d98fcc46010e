"""``rlu.load_dataset(task, source="release")``: download and convert on first use, reuse after.

The converted dataset lives at ``CACHE/datasets/<task>/<family>[/<dataset>][/shards-<sel>]``; a
second call opens it without touching the network (the download manifest is only consulted when
the dataset is missing).
"""

from __future__ import annotations

import fcntl
import hashlib
import os
from collections.abc import Sequence

from rlu.data.release import catalog
from rlu.data.release.convert import convert
from rlu.data.release.download import cache_root, download
from rlu.data.store import Dataset, open_dataset
from rlu.locks import open_private


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
