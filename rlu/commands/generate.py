"""``rlu generate``: record datasets with the paper's recipe (rlu.generate)."""

from __future__ import annotations

import argparse

from rlu.commands.train import add_device_option
from rlu.settings import add_options


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "generate",
        help="record a dataset from online training runs (D4PG / DQN), the paper's recipe",
        description="Plays --seeds independent online training runs, records every episode, "
        "keeps a third of the successful ones and sub-samples to the paper's episode count. "
        "Re-running an interrupted command resumes it (same seed, same bytes).",
    )
    p.add_argument(
        "task",
        help="task id, e.g. control_suite/cartpole_swingup, atari/Pong or rwrl/cartpole_swingup "
        "(rwrl writes OUT/{none,easy}_{small,medium,large})",
    )
    p.add_argument("--out", required=True, help="new dataset directory")
    p.add_argument(
        "--scale",
        default="laptop",
        choices=["tiny", "laptop", "paper"],
        help="laptop (default): behaviour runs that learn in minutes of CPU; tiny: seconds, for "
        "tests; paper: the paper's budgets (clusters)",
    )
    p.add_argument("--seeds", type=int, default=None, help="runs (default: the scale's)")
    p.add_argument("--seed", type=int, default=0, help="base seed of every run")
    p.add_argument("--backend", default="local", choices=["local", "ray"])
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help="local backend: processes running the runs (default: one per run); the bytes do "
        "not depend on it",
    )
    p.add_argument(
        "--curves",
        default=None,
        metavar="PNG",
        help="also draw the runs' learning curves (return vs env steps, one line per run) into "
        "PNG and print each run's level",
    )
    p.add_argument(
        "--policy",
        default=None,
        metavar="MODULE:FACTORY",
        help="record this policy instead of training D4PG/DQN (required for locomotion): "
        "factory(task_id, seed) -> policy(observation) -> action",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument("--keep-work", action="store_true", help="keep the per-run parts afterwards")
    from rlu.workers import Backend

    add_options(p, Backend, only=("gpus_per_job",))
    add_device_option(p)
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
        policy=args.policy,
        device=args.device,
        gpus_per_run=args.gpus_per_job,
        workers=args.workers,
    )
    from pathlib import Path

    paths = [path]
    if (Path(path) / "rwrl.json").exists():  # rwrl: one dataset per challenge and size
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
