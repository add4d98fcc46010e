"""``rlu generate``: record datasets with the paper's recipe (rlu.generate)."""

from __future__ import annotations

import argparse

from rlu.commands._options import add_options, checked, field_docs


def register(sub: argparse._SubParsersAction) -> None:
    from rlu.generate.config import GenerateConfig
    from rlu.workers import Backend

    p = sub.add_parser(
        "generate",
        help="record a dataset from online training runs (D4PG / DQN), the paper's recipe",
        description="Plays --seeds independent online training runs, records every episode, "
        "keeps a third of the successful ones and sub-samples to the paper's episode count. "
        "Re-running an interrupted command resumes it (same seed, same bytes).",
    )
    p.add_argument("task", help=field_docs(GenerateConfig)["task"])
    p.add_argument("--out", required=True, help="new dataset directory")
    add_options(p, GenerateConfig, skip=("task", "backend", "progress"))
    add_options(p, Backend, skip=("workers",))
    p.add_argument(
        "--workers",
        type=checked(int, {"min": 1}, "--workers"),
        default=None,
        metavar="N",
        help="local backend: processes running the runs at once (default: one per run; 3 runs "
        "on 2 cores then take the time of 1.5); the bytes do not depend on it",
    )
    p.add_argument(
        "--curves",
        default=None,
        metavar="PNG",
        help="also draw the runs' learning curves (return vs env steps, one line per run) into "
        "PNG and print each run's level",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import dataclasses
    import time

    from rlu.commands._options import from_args
    from rlu.data import open_dataset
    from rlu.generate import GenerateConfig, generate, run_count
    from rlu.generate.rwrl import SUMMARY
    from rlu.workers import Backend

    t0 = time.perf_counter()
    config = from_args(GenerateConfig, args, task=args.task, progress=not args.no_progress)
    workers = args.workers or (run_count(config) if args.kind == "local" else 1)
    backend = Backend(args.kind, workers, args.address, args.gpus_per_job)
    backend.reach()  # a Ray cluster that does not answer: refused before OUT is made
    path = generate(dataclasses.replace(config, backend=backend), args.out)
    from pathlib import Path

    paths = [path]
    if (Path(path) / SUMMARY).exists():  # rwrl: one dataset per challenge and size
        paths = sorted(p for p in Path(path).iterdir() if (p / "manifest.json").exists())
    for p in paths:
        ds = open_dataset(p)
        r = ds.info()["returns"]
        sel = ds.manifest["provenance"].get("selection")
        made = f" ({sel['recorded']} recorded, {sel['successful']} successful)" if sel else ""
        print(
            f"{p}: {r.get('episodes', 0)} episodes{made}, {ds.num_steps} steps, return mean "
            f"{r.get('mean', float('nan')):.1f} p90 {r.get('p90', float('nan')):.1f}"
        )
    seconds = time.perf_counter() - t0
    if args.curves and paths == [path]:
        from rlu.generate import curves
        from rlu.generate.scales import behaviour_target
        from rlu.tasks import get_task

        runs, prov = curves.dataset_curves(path)
        target = behaviour_target(get_task(args.task))
        print(curves.markdown_table(curves.summarise(runs), target))
        title = prov["command"].removeprefix("rlu generate ").removesuffix(" --out DIR")
        print(f"curves: {curves.plot(runs, args.curves, title, target)}")
    elif args.curves:
        print("--curves: rwrl datasets come from fixed snapshots (no learning curve to draw)")
    print(f"{seconds:.0f}s")
    return 0
