"""``rlu train``, ``rlu evaluate``, ``rlu sweep`` and ``rlu report``.

Defaults chosen by measurement (a 2-core machine shared with other jobs):

- ``--threads 1`` for train and evaluate: torch's default (one thread per core) made D4PG and
  BCQ updates 1.6-14x slower than one thread, and an evaluation with a batch of 4 observations
  per step 4-7x slower; intra-op threads pay off only on idle cores and large batches.
- ``--eval-every``: every ``steps / 10`` steps but at most every ``EVAL_EVERY_MIN`` steps, and
  always at the end. ``steps / 10`` made a 20-step ``rlu train`` of BCQ evaluate 10 times (50
  episodes of 1000 steps; over 5 minutes); now it evaluates once, at the end.
- ``--device auto``: the first CUDA GPU if PyTorch sees one, else the CPU (docs/devices.md);
  the device a run used is in its config.json. The library's own default stays ``cpu``.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from rlu.commands._video import add_video_options, check_video_options, write_run_videos

EVAL_EVERY_MIN = 10_000
"""Fewest gradient steps between two periodic evaluations of ``rlu train``."""


def add_device_option(p: argparse.ArgumentParser) -> None:
    """``--device``, shared by every command that runs an agent (train, evaluate, sweep,
    generate, quickstart, report --fqe)."""
    p.add_argument(
        "--device",
        default="auto",
        metavar="DEVICE",
        help="auto, cpu, cuda or cuda:N (default auto: the first CUDA GPU if there is one)",
    )


def add_gpus_per_run_option(p: argparse.ArgumentParser) -> None:
    """``--gpus-per-run``, shared by the commands that spread runs over Ray (sweep, generate)."""
    p.add_argument(
        "--gpus-per-run",
        type=float,
        default=0.0,
        metavar="F",
        help="Ray: GPUs each run asks for; a fraction shares one (0.25: four runs per GPU)",
    )


def add_runtime_options(p: argparse.ArgumentParser) -> None:
    """How training computes (``rlu.devices.Runtime``): device, precision, TF32, compile and
    the data path."""
    add_device_option(p)
    p.add_argument(
        "--precision",
        default="fp32",
        choices=["fp32", "bf16"],
        help="bf16: updates under bfloat16 autocast (weights and optimiser states stay fp32)",
    )
    p.add_argument("--tf32", action="store_true", help="CUDA: TF32 matmuls and convolutions")
    p.add_argument(
        "--compile", action="store_true", help="torch.compile the agent's modules (opt-in)"
    )
    p.add_argument(
        "--prefetch",
        type=int,
        default=None,
        metavar="N",
        help="batches sampled ahead by a background thread (default: 2 on CUDA, 0 on the CPU)",
    )
    p.add_argument(
        "--data-on-device",
        action="store_true",
        help="hold the dataset on the device and gather batches there (transition batches)",
    )


def runtime_from_args(args: argparse.Namespace) -> Any:
    """The ``rlu.devices.Runtime`` of ``add_runtime_options``' flags."""
    from rlu.devices import Runtime

    return Runtime(
        device=args.device,
        precision=args.precision,
        tf32=args.tf32,
        compile=args.compile,
        prefetch=args.prefetch,
        data_on_device=args.data_on_device,
    )


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--preset",
        default="small",
        help="agent preset: small (CPU minutes), paper, ...",
    )
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help="gradient steps (default: the preset's num_steps, e.g. 2M for the Atari paper preset)",
    )
    p.add_argument(
        "--eval-every",
        type=int,
        default=None,
        help=f"steps between evaluations (default: steps / 10 but at least {EVAL_EVERY_MIN:,} for "
        "train, the end of each run for sweep; 0: only at the end; -1: never)",
    )
    p.add_argument("--eval-episodes", type=int, default=5)
    p.add_argument("--eval-envs", type=int, default=4, help="envs stepped in lockstep")
    p.add_argument(
        "--eval-max-steps", type=int, default=None, help="cap on an evaluation episode's steps"
    )
    p.add_argument("--log-every", type=int, default=100)
    p.add_argument("--checkpoint-every", type=int, default=1000)
    p.add_argument(
        "--env", default=None, help="env factory 'module:function' (default: rlu.envs.make_env)"
    )
    p.add_argument(
        "--challenge",
        default=None,
        choices=["none", "easy"],
        help="RWRL: evaluate under this challenge (default: the one the data was recorded under)",
    )


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train an agent on a dataset, evaluating in the env")
    p.add_argument("--task", required=True, help="task id, e.g. control_suite/cartpole_swingup")
    p.add_argument("--agent", required=True, help="agent name (bc, d4pg, ...) or module path")
    p.add_argument("--dataset", required=True, help="rlu dataset directory")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="run folder")
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint")
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch threads (default 1: faster than one per core on a shared machine)",
    )
    p.add_argument("--tensorboard", action="store_true", help="also log to OUT/tensorboard")
    p.add_argument("--no-progress", action="store_true")
    _add_run_options(p)
    add_runtime_options(p)
    p.add_argument(
        "overrides",
        nargs="*",
        metavar="FIELD=VALUE",
        help="agent config overrides, e.g. learning_rate=3e-4 or atari.batch_size=64",
    )
    p.set_defaults(func=_train)

    p = sub.add_parser("evaluate", help="roll out a trained run's greedy policy in its env")
    p.add_argument("run", metavar="RUN_OR_CHECKPOINT")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--envs", type=int, default=4, help="envs stepped in lockstep")
    p.add_argument("--max-steps", type=int, default=None)
    p.add_argument("--env", default=None, help="env factory 'module:function'")
    p.add_argument(
        "--challenge",
        default=None,
        choices=["none", "easy"],
        help="RWRL: evaluate under this challenge (default: the run's)",
    )
    p.add_argument(
        "--threads", type=int, default=1, help="torch threads (default 1: small batches per step)"
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    add_device_option(p)
    add_video_options(p)
    p.set_defaults(func=_evaluate)

    p = sub.add_parser("sweep", help="tasks x agents x grids x seeds, locally or on Ray")
    p.add_argument("--tasks", nargs="+", required=True)
    p.add_argument("--agents", nargs="+", required=True)
    p.add_argument(
        "--dataset",
        action="append",
        required=True,
        metavar="TASK=PATH",
        help="dataset of a task (repeat per task)",
    )
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument(
        "--grid",
        action="append",
        default=None,
        metavar="FIELD=V1,V2",
        help="grid for every agent instead of each agent's paper grid",
    )
    p.add_argument("--max-configs", type=int, default=None)
    p.add_argument(
        "--task-preset",
        action="append",
        default=[],
        metavar="TASK=PRESET",
        help="preset of one task for the agents that have it (e.g. paper_recurrent)",
    )
    p.add_argument("--backend", default="local", choices=["local", "ray"])
    p.add_argument("--workers", type=int, default=2, help="local pool size")
    p.add_argument("--ray-address", default=None, help="Ray cluster address (default: local)")
    add_gpus_per_run_option(p)
    p.add_argument("--out", required=True)
    _add_run_options(p)
    add_runtime_options(p)
    p.set_defaults(func=_sweep)

    p = sub.add_parser("report", help="tables and figures of sweeps (Markdown, HTML, PNG)")
    p.add_argument(
        "sweep_dirs",
        nargs="+",
        metavar="SWEEP_DIR",
        help="one or more sweep folders, reported together (e.g. an Atari and a control sweep)",
    )
    p.add_argument(
        "--out",
        default=None,
        help="report folder (default: SWEEP_DIR/report; required with several sweeps)",
    )
    p.add_argument(
        "--fqe",
        action="store_true",
        help="first run offline policy selection by FQE (writes SWEEP_DIR/fqe.json per sweep)",
    )
    p.add_argument("--fqe-steps", type=int, default=2000, help="FQE gradient steps")
    add_device_option(p)
    p.set_defaults(func=_report)


def _run_kwargs(args: argparse.Namespace, periodic_eval: bool = True) -> dict:
    # train evaluates up to 10 times, never more often than every EVAL_EVERY_MIN steps (a short
    # run evaluates once, at the end; without --steps, the preset's budget, at the end too); a
    # sweep only at the end of each run
    default_eval = max(EVAL_EVERY_MIN, args.steps // 10) if periodic_eval and args.steps else 0
    return {
        "preset": args.preset,
        "steps": args.steps,
        "eval_every": default_eval if args.eval_every is None else args.eval_every,
        "eval_episodes": args.eval_episodes,
        "eval_envs": args.eval_envs,
        "eval_max_steps": args.eval_max_steps,
        "log_every": args.log_every,
        "checkpoint_every": args.checkpoint_every,
        "env": args.env,
        "challenge": args.challenge,
    }


def _train(args: argparse.Namespace) -> int:
    import sys

    from rlu.train import TrainConfig, parse_overrides, train

    config = TrainConfig(
        task=args.task,
        agent=args.agent,
        dataset=args.dataset,
        seed=args.seed,
        overrides=parse_overrides(args.overrides),
        torch_threads=args.threads,
        runtime=runtime_from_args(args),
        **_run_kwargs(args),
    )
    print(f"rlu train: {args.agent} on {config.runtime.resolve().device}", file=sys.stderr)
    result = train(
        config,
        args.out,
        resume=args.resume,
        progress=not args.no_progress,
        tensorboard=args.tensorboard,
    )
    print(f"{args.out}: step {result['steps']}, final evaluation return {result['score']}")
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from rlu.runs import evaluate_run
    from rlu.types import RluError

    if args.threads < 1:
        raise RluError(f"--threads {args.threads}; use 1 or more")
    if args.video is not None:
        check_video_options(args)
    import torch

    torch.set_num_threads(args.threads)

    res = evaluate_run(
        args.run, args.episodes, args.seed, args.envs, args.env, args.max_steps, args.challenge,
        device=args.device,
    )  # fmt: skip
    if args.json:
        print(json.dumps(res.to_json()))
    else:
        print(
            f"{len(res.returns)} episodes: mean return {res.mean:.3f}, returns "
            + ", ".join(f"{r:.2f}" for r in res.returns)
        )
    if args.video is not None:
        write_run_videos(args)
    return 0


def _sweep(args: argparse.Namespace) -> int:
    from rlu.sweep import SweepConfig, results_table, sweep
    from rlu.train import parse_overrides
    from rlu.types import RluError

    datasets = {}
    for item in args.dataset:
        task, sep, path = item.partition("=")
        if not sep:
            raise RluError(f"--dataset {item!r}; write it as TASK=PATH")
        datasets[task] = path
    grid = None
    if args.grid:
        grid = {}
        for item in args.grid:
            key, sep, values = item.partition("=")
            if not sep:
                raise RluError(f"--grid {item!r}; write it as FIELD=V1,V2")
            grid[key] = [parse_overrides([f"v={v}"])["v"] for v in values.split(",")]
    task_presets = {}
    for item in args.task_preset:
        task, sep, preset = item.partition("=")
        if not sep:
            raise RluError(f"--task-preset {item!r}; write it as TASK=PRESET")
        task_presets[task] = preset
    config = SweepConfig(
        tasks=tuple(args.tasks),
        task_presets=task_presets,
        agents=tuple(args.agents),
        datasets=datasets,
        seeds=tuple(args.seeds),
        grid=grid,
        max_configs=args.max_configs,
        runtime=runtime_from_args(args),
        gpus_per_run=args.gpus_per_run,
        **_run_kwargs(args, periodic_eval=False),
    )
    records = sweep(config, args.out, args.backend, args.workers, args.ray_address, progress=True)
    print(results_table(records), end="")
    return 0


def _report(args: argparse.Namespace) -> int:
    from rlu.evaluation.report import write_report
    from rlu.types import RluError

    if args.out is None and len(args.sweep_dirs) > 1:
        raise RluError(f"{len(args.sweep_dirs)} sweep folders: pass --out for the report folder")
    if args.fqe:
        from rlu.evaluation.fqe import FQEConfig
        from rlu.runs import fqe_selection

        for sweep_dir in args.sweep_dirs:
            fqe_selection(sweep_dir, FQEConfig(steps=args.fqe_steps), args.device)
    paths = write_report(args.sweep_dirs, args.out)
    for p in paths:
        print(f"wrote {p}")
    return 0
