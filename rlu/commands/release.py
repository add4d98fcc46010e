"""``rlu download`` and ``rlu convert``: the original release, fetched and converted."""

from __future__ import annotations

import argparse


def _dataset_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run", help="Atari run: 1..5 or run_1..run_5 (default 1)")
    p.add_argument("--challenge", choices=["none", "easy"], help="RWRL combined challenge")
    p.add_argument("--size", choices=["small", "medium", "large"], help="RWRL dataset size")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("download", help="download release shards of a task into the cache")
    p.add_argument("task", help="task id, e.g. control_suite/cartpole_swingup")
    p.add_argument("--family", help="release family (bucket folder); default: the task's first")
    p.add_argument("--shards", help="shard indices, e.g. 0-3,7 (default: all)")
    _dataset_args(p)
    p.add_argument("--base-url", help="mirror of the bucket (default: the public bucket)")
    p.add_argument("--cache-dir", help="cache directory (default: $RLU_CACHE_DIR or ~/.cache/rlu)")
    p.add_argument("--workers", type=int, default=4, help="parallel downloads")
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
    p.add_argument("--list", action="store_true", help="print the URLs and exit")
    _quiet_arg(p)
    p.set_defaults(func=_download)

    p = sub.add_parser(
        "convert",
        help="convert release shard files into a native dataset",
        description="Convert FILE... (or every shard of the dataset under a bucket-shaped --src "
        "ROOT) into a new dataset at --out. A failed conversion leaves nothing at --out.",
    )
    p.add_argument("files", nargs="*", metavar="FILE", help="shard files")
    p.add_argument(
        "--family",
        required=True,
        help="atari, atari_episodes_ordered, "
        "dm_control_suite, dm_control_suite_episodes, dm_locomotion, "
        "dm_locomotion_episodes, rwrl",
    )
    p.add_argument("--task", required=True, help="task id, e.g. control_suite/cartpole_swingup")
    p.add_argument("--out", required=True, help="new dataset directory")
    p.add_argument("--src", help="bucket-shaped root holding the shards (instead of FILE...)")
    p.add_argument("--shards", help="with --src: shard indices, e.g. 0-3,7")
    _dataset_args(p)
    p.add_argument("--workers", type=int, help="processes (default: one per core)")
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


def _quiet_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--quiet",
        "-q",
        action="store_true",
        help="no progress on stderr (default: a bar with rate and ETA on a terminal, a plain "
        "line every 10 s otherwise; $RLU_PROGRESS=bar|lines|quiet picks one)",
    )


def _download(args: argparse.Namespace) -> int:
    from rlu.data.release import catalog
    from rlu.data.release.download import Downloader
    from rlu.types import RluError

    sel = catalog.select(args.task, args.family, args.run, args.challenge, args.size, args.shards)
    if args.list:
        for u in sel.urls(args.base_url):
            print(u)
        return 0
    if args.timeout <= 0 or args.workers < 1 or args.retries < 0:
        raise RluError("--timeout must be > 0, --workers >= 1 and --retries >= 0")
    d = Downloader(
        cache_dir=args.cache_dir,
        base_url=args.base_url,
        workers=args.workers,
        retries=args.retries,
        timeout=args.timeout,
        allow_redirects=args.allow_redirects,
        progress=not args.quiet,
    )
    got = d.fetch(sel.objects)
    reused = sum(f.reused for f in got)
    total = sum(f.size for f in got)
    what = f"{sel.family} {sel.binding}".strip()
    print(
        f"{len(got)} shards of {sel.task.id} ({what})"
        f" in {d.root}: {total / 1e6:,.1f} MB, {len(got) - reused} downloaded, {reused} reused"
    )
    return 0


def _convert(args: argparse.Namespace) -> int:
    from rlu.data.release import catalog
    from rlu.data.release.convert import convert
    from rlu.tasks import resolve_task
    from rlu.types import RluError

    ref = resolve_task(args.task)  # a TFDS name carries its run or challenge and size
    family, run, challenge, size = ref.dataset_settings(
        args.family, args.run, args.challenge, args.size
    )
    files = list(args.files)
    if args.src:
        if files:
            raise RluError("give either FILE... or --src ROOT, not both")
        sel = catalog.select(ref.task.id, family, run, challenge, size)
        files = catalog.find_shards(args.src, sel, args.shards)
    elif args.shards:
        raise RluError("--shards picks shards under --src; with FILE... list the files instead")
    from rlu.files import check_output

    # --out must not be or hold an input: --overwrite replaces it whole once written
    check_output(args.out, [*files, *([args.src] if args.src else [])], "manifest.json", "dataset")
    if challenge is None and ref.task.domain == "rwrl":
        challenge = _challenge_from_path(files)
    report = convert(
        files,
        family,
        ref.task.id,
        args.out,
        challenge=challenge,
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


def _challenge_from_path(files: list[str]) -> str | None:
    found = {c for f in files for c in ("none", "easy") if f"combined_challenge_{c}" in f}
    return found.pop() if len(found) == 1 else None
