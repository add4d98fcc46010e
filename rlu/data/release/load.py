"""``rlu.load_dataset(task, source="release")``: download and convert on first use, reuse after.

The converted dataset lives at ``CACHE/datasets/<task>/<family>[/<dataset>][/shards-<sel>]``; a
second call opens it without touching the network (the download manifest is only consulted when
the dataset is missing).

``load_task_dataset`` is ``rlu.load_dataset(task)`` (``source="auto"``): what is already on this
machine, never the network. The shipped dataset where one ships and the name picks no release
dataset; else the converted release dataset in the cache; else its shards, downloaded into the
cache earlier (``rlu download``), converted now; else an error naming the ``rlu download``
command that fetches them.

The cache is read as untrusted: an entry is opened only when every folder from the cache's
``datasets/`` down to it is a real folder (a symbolic link there, which could lead out of the
cache, is refused) and its manifest names the task asked for (a dataset of another task moved
or copied there is refused, naming both).
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
from rlu.domains import DOMAINS
from rlu.files import open_private
from rlu.types import RluError

__all__ = [
    "dataset_folder",
    "download_command",
    "load_release_dataset",
    "load_task_dataset",
    "open_cached",
    "release_dataset_path",
]

# Keywords of load_release_dataset that pick a release dataset (so not the shipped one).
_PICKS = ("family", "run", "challenge", "size", "shards")


def release_dataset_path(
    selection: catalog.ReleaseSelection, cache_dir: str | os.PathLike | None, all_shards: bool
) -> str:
    """Where ``load_dataset(source="release")`` keeps the converted dataset of ``selection``."""
    return dataset_folder(os.path.join(cache_root(cache_dir), "datasets"), selection, all_shards)


def dataset_folder(
    root: str | os.PathLike, selection: catalog.ReleaseSelection, all_shards: bool
) -> str:
    """``ROOT/<task>/<family>[/<dataset>][/shards-<sel>]``: the layout of converted datasets
    under a folder (the cache's ``datasets/``, or ``rlu convert --out-root``)."""
    parts = [os.fspath(root), *selection.task.id.split("/"), selection.family]
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
    if _cached(dest, cache_dir):
        return open_cached(dest, sel.task.id, cache_dir)
    os.makedirs(os.path.dirname(dest), exist_ok=True)
    _check_inside_cache(os.path.dirname(dest), cache_dir)
    # never through a planted link (open_private refuses one)
    fd = open_private(dest + ".lock", os.O_RDWR | os.O_CREAT, "dataset lock")
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # two processes loading one dataset: one converts
        if _cached(dest, cache_dir):
            return open_cached(dest, sel.task.id, cache_dir)
        _fetch_and_convert(sel, dest, cache_dir, base_url, workers, progress)
    finally:
        os.close(fd)
    return open_cached(dest, sel.task.id, cache_dir)


def _datasets_root(cache_dir: str | os.PathLike | None) -> str:
    return os.path.join(cache_root(cache_dir), "datasets")


def _check_inside_cache(path: str, cache_dir: str | os.PathLike | None) -> None:
    """Refuse ``path`` when a folder from the cache's ``datasets/`` (itself included) down to it
    is a symbolic link: what lies behind it is outside the cache."""
    root = os.path.abspath(_datasets_root(cache_dir))
    here = os.path.abspath(path)
    while True:
        if os.path.islink(here):
            raise RluError(
                f"{here}: a symbolic link in rlu's dataset cache {root}, which rlu does not "
                f"follow out of the cache; remove the link (rm {here}) and load the dataset "
                "again, or open the folder it points to by its own path"
            )
        if here == root or os.path.dirname(here) == here:
            return
        here = os.path.dirname(here)


def _cached(dest: str, cache_dir: str | os.PathLike | None) -> bool:
    """Whether the cache holds an entry at ``dest`` (a link there counts: it is refused)."""
    return os.path.lexists(os.path.join(dest, "manifest.json")) or os.path.islink(dest)


def open_cached(dest: str, task_id: str, cache_dir: str | os.PathLike | None, **kw: Any) -> Dataset:
    """The dataset of cache entry ``dest``, checked to lie inside the cache (no symbolic link
    from the cache's ``datasets/`` down to its manifest) and to be a dataset of ``task_id``."""
    _check_inside_cache(os.path.join(dest, "manifest.json"), cache_dir)
    ds = open_dataset(dest, **kw)
    if ds.schema.task_id != task_id:
        raise RluError(
            f"{dest}: rlu's cache entry for {task_id} holds a dataset of {ds.schema.task_id!r} "
            f"(its manifest.json says so), not of {task_id}; remove it (rm -r {dest}) and load "
            "the dataset again"
        )
    return ds


def _fetch_and_convert(
    sel: catalog.ReleaseSelection,
    dest: str,
    cache_dir: str | os.PathLike | None,
    base_url: str | None,
    workers: int | None,
    progress: bool | None,
) -> None:
    fetched = download(sel.objects, cache_dir=cache_dir, base_url=base_url, progress=progress)
    kind = DOMAINS[sel.task.domain].datasets
    convert(
        [f.path for f in fetched],
        sel.family,
        sel.task.id,
        dest,
        challenge=sel.binding.split("/")[0] if kind == "challenge_size" else None,
        run=sel.binding if kind in ("runs", "run_names") else None,
        workers=workers,
        progress=progress is not False,
        provenance={
            "dataset": sel.binding,
            "objects": list(sel.objects),
            "sha256": {f.object: f.sha256 for f in fetched},
        },
    )


def load_task_dataset(
    name: str,
    family: str | None = None,
    run: str | int | None = None,
    challenge: str | None = None,
    size: str | None = None,
    cache_dir: str | os.PathLike | None = None,
    shards: str | Sequence[int] | None = None,
    workers: int | None = None,
    progress: bool | None = None,
    verify: bool = False,
) -> Dataset:
    """``rlu.load_dataset(name)`` for a task id or TFDS name: see the module docstring. The
    keywords are ``load_release_dataset``'s (no ``base_url``: this never downloads);
    ``verify=True`` checks every sha256 of a dataset opened as it is."""
    from rlu.data.bundled import bundled_dataset_path, bundled_tasks
    from rlu.tasks import resolve_task

    ref = resolve_task(name)
    task = ref.task
    given = {"family": family, "run": run, "challenge": challenge, "size": size, "shards": shards}
    picked = ref.family is not None or any(given[k] is not None for k in _PICKS)
    shipped = bundled_dataset_path(task.id)
    if shipped is not None and not picked:
        return open_dataset(shipped, verify=verify)
    family, run, challenge, size = ref.dataset_settings(family, run, challenge, size)
    sel = catalog.select(task.id, family, run, challenge, size, shards)
    dest = release_dataset_path(sel, cache_dir, all_shards=shards is None)
    if _cached(dest, cache_dir):
        return open_cached(dest, task.id, cache_dir, verify=verify)
    if _downloaded(sel, cache_dir):
        ds = load_release_dataset(
            task.id, sel.family, run, challenge, size, cache_dir, None, shards, workers, progress
        )
        return open_dataset(ds.path, verify=True) if verify else ds
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
    kind = DOMAINS[sel.task.domain].datasets
    if kind == "runs":
        parts += ["--run", sel.binding.removeprefix("run_")]
    elif kind in ("noise_run", "run_names"):  # bsuite's 0.1/3, DMLab's training_0
        parts += ["--run", sel.binding]
    elif kind == "challenge_size":
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
