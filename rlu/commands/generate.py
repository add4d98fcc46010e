"""``rlu generate``: record datasets with the paper's recipe (rlu.generate.recipe)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "generate",
        help="record a dataset from online training runs (D4PG / DQN), the paper's recipe",
        description="Plays --seeds independent online training runs, records every episode, "
        "keeps a third of the successful ones and sub-samples to the paper's episode count. "
        "Re-running an interrupted command resumes it (same seed, same bytes).",
    )
    p.add_argument("task", help="task id, e.g. control_suite/cartpole_swingup or atari/Pong")
    p.add_argument("--out", required=True, help="new dataset directory")
    p.add_argument("--scale", default="small", choices=["tiny", "small", "paper"])
    p.add_argument("--seeds", type=int, default=None, help="runs (default: the scale's: 2/3/3)")
    p.add_argument("--seed", type=int, default=0, help="base seed of every run")
    p.add_argument("--backend", default="local", choices=["local", "ray"])
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument("--keep-work", action="store_true", help="keep the per-run parts afterwards")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import time

    from rlu.data import open_dataset
    from rlu.generate import generate

    t0 = time.perf_counter()
    path = generate(
        args.task,
        args.out,
        scale=args.scale,
        runs=args.seeds,
        seed=args.seed,
        backend=args.backend,
        progress=not args.no_progress,
        keep_work=args.keep_work,
    )
    ds = open_dataset(path)
    info = ds.info()
    r = info["returns"]
    sel = ds.manifest["provenance"]["selection"]
    print(
        f"{path}: {r.get('episodes', 0)} episodes ({sel['recorded']} recorded, "
        f"{sel['successful']} successful), {ds.num_steps} steps, return mean "
        f"{r.get('mean', float('nan')):.1f} p90 {r.get('p90', float('nan')):.1f}, "
        f"{time.perf_counter() - t0:.0f}s"
    )
    return 0
