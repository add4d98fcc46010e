"""``rlu train``, ``rlu evaluate``, ``rlu sweep`` and ``rlu report``.

The run options (preset, budget, evaluation, checkpoints, threads, runtime) are the fields of
``rlu.settings.RunSettings``, flags and help derived from them, so the library and the command
line share every default. ``--preset small`` is the default: a first ``rlu train`` takes
minutes on a laptop CPU; ``--preset paper`` runs the paper's settings and budget, the only
numbers that stand beside the paper's (with release data). ``--device auto`` (the first CUDA
GPU if PyTorch sees one, else the CPU) is the command line's device; the library's stays cpu.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from rlu.commands._video import add_video_options, check_video_options, write_run_videos
from rlu.loggers import LOGGERS
from rlu.settings import EVAL_EVERY_MIN, add_options, checked, from_args

__all__ = ["EVAL_EVERY_MIN", "add_device_option", "add_backend_options", "register"]


def add_device_option(p: argparse.ArgumentParser) -> None:
    """``--device``, shared by every command that runs an agent (train, evaluate, sweep,
    generate, quickstart, report --fqe): ``rlu.devices.Runtime.device``."""
    from rlu.devices import Runtime

    add_options(p, Runtime, only=("device",))


def add_backend_options(
    p: argparse.ArgumentParser,
    default_workers: int | None = None,
    workers_help: str | None = None,
    gpus: bool = True,
) -> None:
    """``--backend``, ``--workers``, ``--ray-address``, ``--gpus-per-run``: where a fan-out runs
    (``rlu.workers.Backend``), shared by sweep, generate, the quick start, download and convert
    (``gpus=False``: no ``--gpus-per-run``, the jobs need none)."""
    from rlu.workers import Backend

    add_options(p, Backend, skip=("kind", "workers", *(() if gpus else ("gpus_per_job",))))
    add_options(p, Backend, only=("kind",))
    if not gpus:
        p.set_defaults(gpus_per_job=0.0)
    p.add_argument(
        "--workers",
        type=checked(int, {"min": 1}, "--workers"),
        default=default_workers,
        metavar="N",
        help=workers_help
        or "local: processes at once (default: one per core); the results do not depend on it",
    )


def backend_from_args(args: argparse.Namespace, jobs: int | None = None) -> Any:
    """The ``rlu.workers.Backend`` of :func:`add_backend_options`' flags (default workers: one
    per core, never more than ``jobs``)."""
    from rlu.system import available_cores
    from rlu.workers import Backend

    workers = args.workers or min(available_cores(), jobs or available_cores())
    return Backend(args.kind, max(1, workers), args.address, args.gpus_per_job)


def register(sub: argparse._SubParsersAction) -> None:
    from rlu.evaluation.fqe import FQEConfig
    from rlu.settings import RunSettings
    from rlu.sweep import SweepConfig
    from rlu.train import TrainConfig

    p = sub.add_parser(
        "train",
        help="train an agent on a dataset, evaluating in the env",
        allow_abbrev=False,  # a config file's values yield to the options typed in full
    )
    p.add_argument(
        "--config",
        metavar="FILE",
        help="run config as JSON or YAML (the fields of TrainConfig: task, agent, dataset, seed, "
        "overrides, run: {steps, preset, ...}), or a run folder's config.json; options typed "
        "here override it",
    )
    add_options(p, TrainConfig, only=("task", "agent", "seed", "weights"), require=False)
    p.add_argument(
        "--dataset",
        action="extend",
        nargs="+",
        default=None,
        metavar="PATH",
        help="rlu dataset folder; several (repeated, or a glob such as 'runs/Pong_*'): a mixture "
        "of one schema, streamed, weighted by --weights (the first is the evaluation task's) "
        "(required, on the command line or in --config)",
    )
    p.add_argument("--out", required=True, help="run folder (created; an existing one: --resume)")
    p.add_argument("--resume", action="store_true", help="continue from the last checkpoint")
    p.add_argument(
        "--log-to",
        nargs="+",
        default=[],
        choices=list(LOGGERS),
        metavar="LOGGER",
        help="also log metrics to: csv (OUT/metrics.csv, OUT/eval.csv), tensorboard "
        "(OUT/tensorboard; the tensorboard extra), wandb (the wandb extra; WANDB_MODE=offline "
        "writes under OUT/wandb)",
    )
    p.add_argument(
        "--quiet",
        "--no-progress",
        dest="no_progress",
        action="store_true",
        help="no progress (a bar on a terminal, else a plain line every 10 s, on stderr)",
    )
    add_options(p, RunSettings)
    p.add_argument(
        "overrides",
        nargs="*",
        metavar="FIELD=VALUE",
        help="agent config overrides, e.g. learning_rate=3e-4 or atari.batch_size=64",
    )
    p.set_defaults(func=_train, parser=p)

    p = sub.add_parser("evaluate", help="roll out a trained run's greedy policy in its env")
    p.add_argument("run", metavar="RUN_OR_CHECKPOINT")
    p.add_argument(
        "--episodes", type=_count, default=10, metavar="N", help="env episodes (default: 10)"
    )
    p.add_argument("--seed", type=_seed, default=0, help="seeds the episodes (default: 0)")
    p.add_argument(
        "--envs",
        type=_count,
        default=4,
        metavar="N",
        help="envs stepped in lockstep (default: 4; returns do not depend on it)",
    )
    p.add_argument(
        "--max-steps",
        type=_count,
        default=None,
        metavar="N",
        help="cap on an episode's steps (default: the env's limit)",
    )
    p.add_argument(
        "--env",
        default=None,
        metavar="MODULE:FUNCTION",
        help="env factory (a run trained with one needs it named again here: a module named in "
        "a run's files is never imported)",
    )
    p.add_argument(
        "--agent",
        default=None,
        metavar="MODULE",
        help="the agent module a run of an agent outside rlu was trained with (imported because "
        "you typed it; it must be the one its config.json names)",
    )
    p.add_argument(
        "--challenge",
        default=None,
        choices=["none", "easy"],
        help="RWRL: evaluate under this challenge (default: the run's)",
    )
    p.add_argument(
        "--threads",
        type=_count,
        default=1,
        metavar="N",
        help="torch threads (default: 1; small batches per step)",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    add_device_option(p)
    add_video_options(p)
    p.set_defaults(func=_evaluate)

    p = sub.add_parser(
        "sweep",
        help="tasks x agents x grids x seeds, locally or on Ray",
        description="Train every (task, agent, grid configuration, seed) and collect the final "
        "scores. Without --grid each agent's paper grid is expanded (the plan is printed "
        "first). Runs default to --preset small (minutes each on a CPU); numbers to stand "
        "beside the paper's need --preset paper (the paper's settings and budget) on release "
        "data.",
    )
    add_options(p, SweepConfig, only=("tasks", "agents", "seeds", "max_configs"))
    p.add_argument(
        "--dataset",
        action="append",
        required=True,
        metavar="TASK=PATH",
        help="dataset of a task (repeat per task)",
    )
    p.add_argument(
        "--grid",
        action="append",
        default=None,
        metavar="FIELD=V1,V2",
        help="grid for every agent instead of each agent's paper grid",
    )
    p.add_argument(
        "--task-preset",
        action="append",
        default=[],
        metavar="TASK=PRESET",
        help="preset of one task for the agents that have it (e.g. paper_recurrent)",
    )
    add_backend_options(p, default_workers=2)
    p.add_argument("--out", required=True, help="sweep folder (an existing one is continued)")
    add_options(p, RunSettings)
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
    add_options(p, FQEConfig, only=("steps",), flag_prefix="--fqe-", dest_prefix="fqe_")
    add_device_option(p)
    p.set_defaults(func=_report)


_count = checked(int, {"min": 1}, "this option")
_seed = checked(int, {"min": 0}, "--seed")


def _train(args: argparse.Namespace) -> int:
    import sys

    from rlu.settings import RunSettings
    from rlu.train import TrainConfig, parse_overrides, train
    from rlu.types import RluError

    overrides = parse_overrides(args.overrides)
    if args.config is not None:
        overrides = {**_from_config_file(args), **overrides}
    for name in ("task", "agent", "dataset"):
        if getattr(args, name) is None:
            raise RluError(f"--{name} is missing: give it on the command line or in --config")
    paths = _dataset_paths(args.dataset)
    config = from_args(
        TrainConfig,
        args,
        dataset=paths[0] if len(paths) == 1 else paths,
        weights=None if args.weights is None else tuple(args.weights),
        overrides=overrides,
        run=from_args(RunSettings, args),
    )
    print(f"rlu train: {args.agent} on {config.run.runtime.resolve().device}", file=sys.stderr)
    result = train(
        config,
        args.out,
        resume=args.resume,
        progress=not args.no_progress,
        loggers=args.log_to,
    )
    print(
        f"{args.out}: {result['steps']} steps ({result['preset']} preset), final evaluation "
        f"return {_score(result['score'])} over {result['eval_episodes']} episodes"
    )
    return 0


def _dataset_paths(given: str | list[str]) -> tuple[str, ...]:
    """``--dataset`` values (or a config file's) with globs expanded, in order."""
    import glob
    import os

    from rlu.types import RluError

    out: list[str] = []
    for item in [given] if isinstance(given, str) else given:
        if glob.has_magic(item) and not os.path.exists(item):
            found = sorted(glob.glob(item))
            if not found:
                raise RluError(f"--dataset {item!r} matches no dataset folder")
            out += found
        else:
            out.append(item)
    return tuple(out)


def _from_config_file(args: argparse.Namespace) -> dict[str, Any]:
    """Fill the options the user did not type from ``--config``; returns its overrides. A module
    path the file names (agent, env factory) is refused unless typed too: names in files are
    never imported."""
    from rlu.settings import RunSettings, flat_values, read_config_file, typed_dests
    from rlu.train import TrainConfig

    data = read_config_file(args.config, TrainConfig)
    typed = typed_dests(args.parser, args.argv)
    values = flat_values(TrainConfig, {k: v for k, v in data.items() if k != "run"})
    values.pop("overrides", None)
    values.update(flat_values(RunSettings, data.get("run", {})))
    for dest, value in values.items():
        if dest not in typed:
            setattr(args, dest, value)
    from rlu.types import RluError

    for dest, what in (("agent", "an agent module"), ("env", "an env factory")):
        value = getattr(args, dest)
        named = value is not None and (dest == "env" or "." in value)
        if dest not in typed and named:
            raise RluError(
                f"{args.config}: field {dest!r} names {what} ({value!r}), and a module named in "
                f"a file is never imported; if you trust it, type it: --{dest} {value}"
            )
    return dict(data.get("overrides", {}))


def _score(value: float | None) -> str:
    return "not evaluated" if value is None else f"{value:.1f}"


def _evaluate(args: argparse.Namespace) -> int:
    from rlu.restore import evaluate_run

    if args.agent is not None:
        from rlu.agents import trust_agent

        trust_agent(args.agent)
    if args.env is not None:
        from rlu.evaluation.rollout import trust_env_factory

        trust_env_factory(args.env)
    if args.video is not None:
        check_video_options(args)
    import torch

    torch.set_num_threads(args.threads)

    res = evaluate_run(
        args.run,
        args.episodes,
        args.seed,
        args.envs,
        args.env,
        args.max_steps,
        args.challenge,
        device=args.device,
    )
    if args.json:
        print(json.dumps(res.to_json()))
    else:
        print(
            f"{len(res.returns)} episodes: mean return {res.mean:.1f}, returns "
            + ", ".join(f"{r:.1f}" for r in res.returns)
        )
    if args.video is not None:
        write_run_videos(args)
    return 0


def _pairs(items: list[str], flag: str, what: str) -> dict[str, str]:
    from rlu.types import RluError

    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key or not value:
            raise RluError(f"{flag} {item!r}; write it as {what}")
        out[key] = value
    return out


def _sweep(args: argparse.Namespace) -> int:
    from rlu.settings import RunSettings
    from rlu.sweep import SweepConfig, results_table, sweep
    from rlu.train import parse_overrides

    grid = None
    if args.grid:
        grid = {
            key: [parse_overrides([f"v={v}"])["v"] for v in values.split(",")]
            for key, values in _pairs(args.grid, "--grid", "FIELD=V1,V2").items()
        }
    config = from_args(
        SweepConfig,
        args,
        datasets=_pairs(args.dataset, "--dataset", "TASK=PATH"),
        grid=grid,
        task_presets=_pairs(args.task_preset, "--task-preset", "TASK=PRESET"),
        run=from_args(RunSettings, args),
    )
    records = sweep(config, args.out, backend_from_args(args), progress=True)
    print(results_table(records), end="")
    return 0


def _report(args: argparse.Namespace) -> int:
    from rlu.evaluation.report import write_report
    from rlu.types import RluError

    if args.out is None and len(args.sweep_dirs) > 1:
        raise RluError(f"{len(args.sweep_dirs)} sweep folders: pass --out for the report folder")
    if args.fqe:
        from rlu.evaluation.fqe import FQEConfig
        from rlu.restore import fqe_selection

        for sweep_dir in args.sweep_dirs:
            fqe_selection(sweep_dir, FQEConfig(steps=args.fqe_steps), args.device)
    from rlu.agents import paper_steps

    paths = write_report(args.sweep_dirs, args.out, paper_steps=paper_steps)
    for p in paths:
        print(f"wrote {p}")
    return 0
