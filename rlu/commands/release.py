"""``rlu download`` and ``rlu convert``: the original release, fetched and converted."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from rlu.domains import DOMAINS

if TYPE_CHECKING:  # pragma: no cover
    from rlu.data.release.catalog import ReleaseSelection
    from rlu.domains.spec import TaskRef


def _dataset_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--run",
        help="the dataset's run: Atari 1..5 or run_1..run_5, bsuite NOISE/RUN (0.1/3), DeepMind "
        "Lab training_0..2 or seekavoid's snapshot_K_eps_E (default: the first)",
    )
    p.add_argument("--challenge", choices=["none", "easy"], help="RWRL combined challenge")
    p.add_argument("--size", choices=["small", "medium", "large"], help="RWRL dataset size")


def _family_names() -> list[str]:
    """The release families the registered tasks' files are in, in the domains' order."""
    from rlu.tasks import list_tasks

    return list(dict.fromkeys(rel.family for t in list_tasks() for rel in t.release))


def register(sub: argparse._SubParsersAction) -> None:
    """``rlu download`` and ``rlu convert``."""
    _register_download(sub)
    _register_convert(sub)


def _register_download(sub: argparse._SubParsersAction) -> None:
    from rlu.commands.train import add_backend_options

    p = sub.add_parser(
        "download",
        help="download release shards of tasks into the cache",
        description="Download (or reuse, verified) the shards of each TASK's dataset into the "
        "cache. --backend ray: one Ray task per shard over a cluster, into a --cache-dir every "
        "node sees (docs/cluster.md).",
    )
    p.add_argument(
        "task",
        nargs="+",
        help="task ids, e.g. control_suite/cartpole_swingup; patterns such as 'atari/*' (every "
        "Atari game) and comma lists work",
    )
    p.add_argument("--family", help="release family (bucket folder); default: the task's first")
    p.add_argument("--shards", help="shard indices, e.g. 0-3,7 (default: all)")
    _dataset_args(p)
    p.add_argument("--base-url", help="mirror of the bucket (default: the public bucket)")
    p.add_argument("--cache-dir", help="cache directory (default: $RLU_CACHE_DIR or ~/.cache/rlu)")
    _fetch_args(p)
    p.add_argument("--list", action="store_true", help="print the URLs and exit")
    add_backend_options(
        p, workers_help="local: parallel downloads (default 4); Ray: one task per shard", gpus=False
    )
    _quiet_arg(p)
    p.set_defaults(func=_download)


def _register_convert(sub: argparse._SubParsersAction) -> None:
    from rlu.commands.train import add_backend_options

    p = sub.add_parser(
        "convert",
        help="convert release shard files into native datasets",
        description="Convert FILE... (or every shard of the dataset under a bucket-shaped --src "
        "ROOT, or with --download the shards fetched into the cache) into a new dataset at "
        "--out, or one dataset per task under --out-root. A failed conversion leaves nothing "
        "at --out. With --backend ray, --out-root or --download every shard is its own job "
        "(on a Ray cluster, over storage every node sees: docs/cluster.md), and a job run "
        "again converts only the shards it had not finished.",
    )
    p.add_argument("files", nargs="*", metavar="FILE", help="shard files")
    p.add_argument(
        "--family",
        required=True,
        help=", ".join(_family_names()),
    )
    p.add_argument(
        "--task",
        required=True,
        action="append",
        help="task id, e.g. control_suite/cartpole_swingup; repeat it, or give a comma list or a "
        "pattern such as 'atari/*', for one dataset per task (with --out-root)",
    )
    out = p.add_mutually_exclusive_group()
    out.add_argument("--out", help="new dataset directory (one task)")
    out.add_argument(
        "--out-root",
        help="folder of datasets: each at OUT_ROOT/<task>/<family>/<dataset>, the cache's layout "
        "(default with --download: the cache's datasets/, where rlu.load_dataset finds them)",
    )
    p.add_argument("--src", help="bucket-shaped root holding the shards (instead of FILE...)")
    p.add_argument("--shards", help="with --src or --download: shard indices, e.g. 0-3,7")
    _dataset_args(p)
    p.add_argument(
        "--download",
        action="store_true",
        help="fetch the shards into the cache first (or reuse them, verified), each in its "
        "shard's job",
    )
    p.add_argument("--cache-dir", help="with --download: the cache (default: $RLU_CACHE_DIR)")
    p.add_argument("--base-url", help="with --download: a mirror of the bucket")
    _fetch_args(p)
    add_backend_options(
        p,
        workers_help="local: processes (default: one per core); the output does not depend on it",
        gpus=False,
    )
    p.add_argument(
        "--skip-corrupt",
        action="store_true",
        help="drop damaged records and report how many, instead of failing",
    )
    p.add_argument("--no-verify", action="store_true", help="skip the record CRC checks")
    p.add_argument(
        "--image-encoding",
        choices=["raw", "zlib"],
        help="store images raw or zlib-compressed (default: zlib for Atari)",
    )
    p.add_argument("--overwrite", action="store_true")
    _quiet_arg(p)
    p.set_defaults(func=_convert)


def _fetch_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--retries", type=int, default=5)
    p.add_argument(
        "--timeout",
        type=float,
        default=30.0,
        help="seconds a connection may stay silent before the attempt fails (default 30)",
    )
    p.add_argument(
        "--allow-redirects",
        action="store_true",
        help="follow redirects to other hosts (a mirror behind a CDN); same-host ones always are",
    )


def _quiet_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--quiet",
        "-q",
        action="store_true",
        help="no progress on stderr (default: a bar with rate and ETA on a terminal, a plain "
        "line every 10 s otherwise; $RLU_PROGRESS=bar|lines|quiet picks one)",
    )


def _check_fetch_args(args: argparse.Namespace) -> None:
    from rlu.types import RluError

    if args.timeout <= 0 or args.retries < 0:
        raise RluError("--timeout must be > 0 and --retries >= 0")


def _fetch(args: argparse.Namespace) -> Any:
    from rlu.data.release.download import cache_root
    from rlu.data.release.jobs import Fetch

    return Fetch(
        cache_dir=cache_root(args.cache_dir),
        base_url=args.base_url,
        retries=args.retries,
        timeout=args.timeout,
        allow_redirects=args.allow_redirects,
    )


def _download(args: argparse.Namespace) -> int:
    from rlu.commands.train import backend_from_args
    from rlu.data.release import catalog
    from rlu.data.release.download import Downloader

    sels = [
        catalog.select(t, args.family, args.run, args.challenge, args.size, args.shards)
        for t in catalog.expand_tasks(args.task)
    ]
    if args.list:
        for sel in sels:
            for u in sel.urls(args.base_url):
                print(u)
        return 0
    _check_fetch_args(args)
    backend = backend_from_args(args)  # a bad or dead --ray-address: refused before the cache
    objects = [o for sel in sels for o in sel.objects]
    if args.kind == "ray":
        from rlu.data.release.jobs import fetch_release

        fetch = _fetch(args)
        got = fetch_release(objects, backend, fetch, progress=not args.quiet)
        root = fetch.cache_dir
    else:
        d = Downloader(
            cache_dir=args.cache_dir,
            base_url=args.base_url,
            workers=args.workers or 4,
            retries=args.retries,
            timeout=args.timeout,
            allow_redirects=args.allow_redirects,
            progress=not args.quiet,
        )
        got = d.fetch(objects)
        root = d.root
    by_object = {f.object: f for f in got}
    for sel in sels:
        mine = [by_object[o] for o in sel.objects]
        reused = sum(f.reused for f in mine)
        total = sum(f.size for f in mine)
        what = f"{sel.family} {sel.binding}".strip()
        print(
            f"{len(mine)} shards of {sel.task.id} ({what})"
            f" in {root}: {total / 1e6:,.1f} MB, {len(mine) - reused} downloaded, {reused} reused"
        )
    return 0


def _convert(args: argparse.Namespace) -> int:
    from rlu.commands.train import backend_from_args
    from rlu.data.release import catalog
    from rlu.types import RluError

    tasks = catalog.expand_tasks(args.task)
    if args.download and (args.src or args.files):
        raise RluError("--download fetches the shards itself; drop --src and FILE...")
    if not args.download and (args.cache_dir or args.base_url):
        raise RluError("--cache-dir and --base-url go with --download")
    if args.src and args.files:
        raise RluError("give either FILE... or --src ROOT, not both")
    if args.shards and not (args.src or args.download):
        raise RluError("--shards picks shards under --src; with FILE... list the files instead")
    if args.files and len(tasks) > 1:
        raise RluError("FILE... are the shards of one dataset: give one --task, or use --src")
    if len(tasks) > 1 and args.out:
        raise RluError(f"{len(tasks)} tasks make {len(tasks)} datasets: give --out-root, not --out")
    if not (args.out or args.out_root or args.download):
        raise RluError("say where the dataset goes: --out DIR (or --out-root ROOT)")
    backend = backend_from_args(args)  # a bad or dead --ray-address: refused before any output
    sharded = args.kind == "ray" or bool(args.out_root) or args.download or len(tasks) > 1
    if sharded:
        return _convert_job(args, tasks, backend)
    return _convert_local(args, tasks[0])


def _selection(
    args: argparse.Namespace, task: str
) -> tuple[TaskRef, ReleaseSelection, str | int | None]:
    """(task ref, catalog selection, run) of one --task with the dataset flags."""
    from rlu.data.release import catalog
    from rlu.tasks import resolve_task

    ref = resolve_task(task)  # a TFDS name carries its run or challenge and size
    family, run, challenge, size = ref.dataset_settings(
        args.family, args.run, args.challenge, args.size
    )
    shards = args.shards if args.download else None
    sel = catalog.select(ref.task.id, family, run, challenge, size, shards)
    return ref, sel, run


def _convert_local(args: argparse.Namespace, task: str) -> int:
    from rlu.data.release import catalog
    from rlu.data.release.convert import convert
    from rlu.files import check_output
    from rlu.tasks import resolve_task

    ref = resolve_task(task)  # a TFDS name carries its run or challenge and size
    family, run, challenge, size = ref.dataset_settings(
        args.family, args.run, args.challenge, args.size
    )
    assert family is not None  # convert's --family is required
    files = list(args.files)
    if args.src:
        sel = catalog.select(ref.task.id, family, run, challenge, size)
        files = catalog.find_shards(args.src, sel, args.shards)
    # --out must not be or hold an input: --overwrite replaces it whole once written
    check_output(args.out, [*files, *([args.src] if args.src else [])], "manifest.json", "dataset")
    report = convert(
        files,
        family,
        ref.task.id,
        args.out,
        challenge=_rwrl_challenge(ref, args, files),
        run=run,
        workers=args.workers,
        verify=not args.no_verify,
        on_error="skip" if args.skip_corrupt else "raise",
        image_encoding=args.image_encoding,
        overwrite=args.overwrite,
        progress=not args.quiet,
    )
    print(
        f"wrote {report.out}: {report.segments:,} segments, {report.steps:,} steps from "
        f"{report.records:,} records of {len(report.files)} shards in {report.seconds:.1f} s"
    )
    if report.skipped:
        print(f"skipped {report.skipped} damaged records (--skip-corrupt)")
    return 0


def _rwrl_challenge(ref: Any, args: argparse.Namespace, files: list[str]) -> str | None:
    """The RWRL challenge as the local conversion takes it: the flag (or the TFDS name), else
    the files' path."""
    _, _, challenge, _ = ref.dataset_settings(args.family, args.run, args.challenge, args.size)
    if challenge is None and DOMAINS[ref.task.domain].challenges:
        challenge = _challenge_from_path(files)
    return challenge


def _convert_job(args: argparse.Namespace, tasks: list[str], backend: Any) -> int:
    import os

    from rlu.data.release import catalog
    from rlu.data.release.download import cache_root
    from rlu.data.release.jobs import DatasetJob, convert_release
    from rlu.data.release.load import dataset_folder

    fetch = None
    if args.download:
        _check_fetch_args(args)
        fetch = _fetch(args)
    root = args.out_root or (os.path.join(cache_root(args.cache_dir), "datasets"))
    jobs = []
    for task in tasks:
        ref, sel, run = _selection(args, task)
        if fetch is not None:
            shards = list(sel.objects)
            kind = DOMAINS[ref.task.domain].datasets
            challenge = sel.binding.split("/")[0] if kind == "challenge_size" else None
            run = sel.binding if kind in ("runs", "run_names") else None  # as load_dataset does
        else:
            shards = catalog.find_shards(args.src, sel, args.shards) if args.src else args.files
            challenge = _rwrl_challenge(ref, args, shards)
        whole = args.shards is None and not args.files
        out = args.out or dataset_folder(root, sel, all_shards=whole)
        jobs.append(
            DatasetJob(
                ref.task.id, sel.family, out, tuple(shards), sel.binding, challenge,
                None if run is None else str(run),
            )
        )  # fmt: skip
    report = convert_release(
        jobs,
        backend,
        fetch=fetch,
        verify=not args.no_verify,
        on_error="skip" if args.skip_corrupt else "raise",
        image_encoding=args.image_encoding,
        overwrite=args.overwrite,
        progress=not args.quiet,
    )
    for line in report.summary():
        print(line)
    return 0


def _challenge_from_path(files: list[str]) -> str | None:
    found = {c for f in files for c in ("none", "easy") if f"combined_challenge_{c}" in f}
    return found.pop() if len(found) == 1 else None
