"""``rlu train``, ``rlu evaluate``, ``rlu sweep`` and ``rlu report``.

The run options (preset, budget, evaluation, checkpoints, threads, runtime) are the fields of
``rlu.training.config.RunSettings``, flags and help derived from them, so the library and the
command line share every default. ``--preset small`` is the default: a first ``rlu train`` takes
minutes on a laptop CPU; ``--preset paper`` runs rlu's paper presets (the paper's settings; the
paper's budget where it states one, Atari's 2M, rlu's elsewhere), and ``rlu report`` checks
every other condition of the paper's numbers before it calls a number comparable
(``rlu.report.conditions``). ``--device auto`` (the first CUDA
GPU if PyTorch sees one, else the CPU) is the command line's device; the library's stays cpu.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from rlu.commands._options import add_options, checked, from_args
from rlu.commands._video import (
    add_video_options,
    check_video_options,
    evaluation_watch,
    report_videos,
)
from rlu.training.config import EVAL_EVERY_MIN
from rlu.training.loggers import LOGGERS

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
    per core, never more than ``jobs``), its Ray address checked and, a HOST:PORT one, reached
    (``Backend.reach``: a cluster that does not answer is refused in seconds, before the command
    makes its output folder)."""
    from rlu.system import available_cores
    from rlu.workers import Backend

    workers = args.workers or min(available_cores(), jobs or available_cores())
    backend = Backend(args.kind, max(1, workers), args.address, args.gpus_per_job)
    backend.reach()
    return backend


def register(sub: argparse._SubParsersAction) -> None:
    """``rlu train``, ``rlu evaluate``, ``rlu sweep`` and ``rlu report``."""
    _register_train(sub)
    _register_evaluate(sub)
    _register_sweep(sub)
    _register_report(sub)


def _register_train(sub: argparse._SubParsersAction) -> None:
    from rlu.training.config import RunSettings
    from rlu.training.prepare import TrainConfig

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
        help="the data, as rlu.load_dataset names it (a task id, a TFDS name or a dataset "
        "folder); several (repeated, or a glob such as 'runs/Pong_*'): a mixture of one schema, "
        "streamed, weighted by --weights (the first is the evaluation task's) (required, on the "
        "command line or in --config)",
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
        help="agent config overrides, e.g. learning_rate=3e-4, atari.batch_size=64 or "
        "recurrent=true (a boolean: true or false, as in a YAML config)",
    )
    p.set_defaults(func=_train, parser=p)


def _register_evaluate(sub: argparse._SubParsersAction) -> None:
    from rlu.training.config import RunSettings

    p = sub.add_parser(
        "evaluate",
        help="roll out a trained run's greedy policy in its env",
        description="Roll out the greedy policy of a run's newest checkpoint (or of a given "
        "checkpoint) in the env the run evaluated in. The evaluation options are rlu train's, "
        "with the same names and defaults.",
    )
    p.add_argument("run", metavar="RUN_OR_CHECKPOINT")
    p.add_argument("--seed", type=_seed, default=0, help="seeds the episodes (default: 0)")
    add_options(
        p,
        RunSettings,
        only=("eval_episodes", "eval_envs", "eval_max_steps", "env", "challenge", "torch_threads"),
    )
    for old, dest, lo in (("--episodes", "eval_episodes", 1), ("--envs", "eval_envs", 1),
                          ("--max-steps", "eval_max_steps", 1)):  # fmt: skip
        # the names evaluate had before it took train's: still read, no longer shown
        p.add_argument(old, dest=dest, type=checked(int, {"min": lo}, old),
                       default=argparse.SUPPRESS, help=argparse.SUPPRESS)  # fmt: skip
    p.add_argument(
        "--agent",
        default=None,
        metavar="MODULE",
        help="the agent module a run of an agent outside rlu was trained with (imported because "
        "you typed it; it must be the one its config.json names)",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument(
        "--quiet",
        "--no-progress",
        dest="no_progress",
        action="store_true",
        help="no progress (a bar on a terminal, else a plain line every 10 s, on stderr)",
    )
    add_device_option(p)
    add_video_options(p)
    p.set_defaults(func=_evaluate)


def _register_sweep(sub: argparse._SubParsersAction) -> None:
    from rlu.training.config import RunSettings
    from rlu.training.sweep import SweepConfig

    p = sub.add_parser(
        "sweep",
        help="tasks x agents x grids x seeds, locally or on Ray",
        description="Train every (task, agent, grid configuration, seed) and collect the final "
        "scores. Without --grid each agent's paper grid is expanded (the plan is printed "
        "first). Runs default to --preset small (minutes each on a CPU); a number that "
        "compares with the paper's needs --preset paper on the release's data, and rlu report "
        "checks every condition of the paper's number (docs/evaluation.md).",
        allow_abbrev=False,  # a config file's values yield to the options typed in full
    )
    p.add_argument(
        "--config",
        metavar="FILE",
        help="sweep config as JSON or YAML (the fields of SweepConfig: tasks, agents, datasets, "
        "seeds, grid, max_configs, task_presets, loggers, run: {steps, preset, ...}), a sweep "
        "folder's sweep.json, or a run config that rlu train --config takes (its task, agent, "
        "dataset, seed and overrides: a sweep of one run); options typed here override it",
    )
    add_options(p, SweepConfig, only=("tasks", "agents", "seeds", "max_configs"), require=False)
    p.add_argument(
        "--dataset",
        action="append",
        default=[],
        metavar="[TASK=]DATASET",
        help="the data of a task, as rlu.load_dataset names it (a task id, a TFDS name or a "
        "folder; TASK= may be left out: the dataset's own task); repeat per task (default: "
        "the --config file's, else each task's own dataset, the one rlu ships or the release's "
        "in the cache)",
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
        default=None,
        metavar="TASK=PRESET",
        help="preset of one task for the agents that have it (e.g. paper_recurrent)",
    )
    add_options(p, SweepConfig, only=("loggers",))
    add_backend_options(p, default_workers=2)
    p.add_argument("--out", required=True, help="sweep folder (an existing one is continued)")
    add_options(p, RunSettings)
    p.set_defaults(func=_sweep, parser=p)


def _register_report(sub: argparse._SubParsersAction) -> None:
    from rlu.evaluation.fqe import FQEConfig

    p = sub.add_parser(
        "report",
        help="tables and figures of runs and sweeps (Markdown, HTML, PNG)",
        description="Report run folders (rlu train --out) and sweep folders (rlu sweep --out), "
        "any mix, together: runs are grouped by the task, agent, configuration and seed each "
        "recorded. Tables under the paper's protocols, learning curves, rliable's performance "
        "profiles and probability of improvement, each number labelled with what produced it "
        "and, beside the paper's, which of the paper's conditions it meets.",
    )
    p.add_argument(
        "paths",
        nargs="+",
        metavar="RUN_OR_SWEEP",
        help="run folders and sweep folders, reported together",
    )
    p.add_argument(
        "--out",
        default=None,
        help="report folder (default: RUN_OR_SWEEP/report for one folder; required with "
        "several); a folder holding anything but an earlier rlu report is refused",
    )
    p.add_argument(
        "--fqe",
        action="store_true",
        help="first run offline policy selection by FQE (writes SWEEP/fqe.json per sweep)",
    )
    add_options(p, FQEConfig, only=("steps",), flag_prefix="--fqe-", dest_prefix="fqe_")
    add_device_option(p)
    p.set_defaults(func=_report)


_count = checked(int, {"min": 1}, "this option")
_seed = checked(int, {"min": 0}, "--seed")


def _train(args: argparse.Namespace) -> int:
    import sys

    from rlu.commands._options import parse_overrides
    from rlu.training.config import RunSettings
    from rlu.training.prepare import TrainConfig, check_agent_config
    from rlu.training.train import train
    from rlu.types import RluError

    overrides = parse_overrides(args.overrides)
    origins = {key: "the command line" for key in overrides}
    if args.config is not None:
        from_file = _from_config_file(args)
        origins = {key: f"{args.config}: overrides.{key}" for key in from_file} | origins
        overrides = {**from_file, **overrides}
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
    check_agent_config(config, origins)  # before the device, the data or a folder
    print(f"rlu train: {args.agent} on {config.run.runtime.resolve().device}", file=sys.stderr)
    result = train(
        config,
        args.out,
        resume=args.resume,
        progress=not args.no_progress,
        loggers=args.log_to,
    )
    done = f"{args.out}: {result['steps']} steps ({result['preset']} preset)"
    if result["score"] is None:  # --eval-every -1: the run never met its env
        print(f"{done}, not evaluated (--eval-every -1); score it with `rlu evaluate {args.out}`")
    else:
        print(
            f"{done}, final evaluation return {result['score']:.1f} over "
            f"{result['eval_episodes']} episodes"
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
    from rlu.commands._options import flat_values, typed_dests
    from rlu.training.config import RunSettings, read_config_file
    from rlu.training.prepare import TrainConfig

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


def _evaluate(args: argparse.Namespace) -> int:
    from rlu.training.restore import evaluate_run

    if args.agent is not None:
        from rlu.agents import trust_agent

        trust_agent(args.agent)
    if args.env is not None:
        from rlu.evaluation.rollout import trust_env_factory

        trust_env_factory(args.env)
    if args.video is not None:
        check_video_options(args)  # before any work: a bad folder or a missing extra fails now
    import torch

    torch.set_num_threads(args.torch_threads)

    from rlu.progress import Progress

    with (
        Progress(args.eval_episodes, "evaluate", "episodes", quiet=args.no_progress) as bar,
        evaluation_watch(args, bar) as watch,
    ):
        res = evaluate_run(
            args.run,
            args.eval_episodes,
            args.seed,
            args.eval_envs,
            args.env,
            args.eval_max_steps,
            args.challenge,
            device=args.device,
            observer=watch,
            render=watch.render,
        )
    if args.json:
        print(json.dumps(res.to_json()))
    else:
        print(
            f"{len(res.returns)} episodes: mean return {res.mean:.1f}, returns "
            + ", ".join(f"{r:.1f}" for r in res.returns)
        )
    if watch.recorder is not None:
        report_videos(args, watch.recorder)
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


def _datasets(items: list[str]) -> dict[str, str]:
    """``--dataset [TASK=]DATASET`` of a sweep: a bare DATASET is the data of its own task (the
    task a task id or TFDS name names, or a folder's manifest)."""
    from rlu.data import load_dataset
    from rlu.types import RluError

    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            value = item
            key = load_dataset(item).schema.task_id or ""
            if not key:
                raise RluError(f"--dataset {item}: its manifest names no task; write TASK={item}")
        elif not key or not value:
            raise RluError(f"--dataset {item!r}; write it as TASK=DATASET or DATASET")
        if key in out:
            raise RluError(f"--dataset: two datasets for {key} ({out[key]}, {value}); give one")
        out[key] = value
    return out


def _sweep(args: argparse.Namespace) -> int:
    from rlu.commands._options import parse_overrides
    from rlu.training.config import RunSettings
    from rlu.training.sweep import SweepConfig, results_table, sweep
    from rlu.types import RluError

    given = _sweep_config_file(args) if args.config is not None else {}
    datasets = {**given.get("datasets", {}), **_datasets(args.dataset)}
    task_presets = {**given.get("task_presets", {}),
                    **_pairs(args.task_preset or [], "--task-preset", "TASK=PRESET")}  # fmt: skip
    grid = given.get("grid")
    if args.grid:
        grid = {
            key: [parse_overrides([f"v={v}"])["v"] for v in values.split(",")]
            for key, values in _pairs(args.grid, "--grid", "FIELD=V1,V2").items()
        }
    for name, flag in (("tasks", "--tasks"), ("agents", "--agents")):
        if not getattr(args, name):
            raise RluError(f"{flag} is missing: give it on the command line or in --config")
    config = from_args(
        SweepConfig,
        args,
        datasets=datasets,
        grid=grid,
        task_presets=task_presets,
        run=from_args(RunSettings, args),
    )
    records = sweep(config, args.out, backend_from_args(args), progress=True)
    print(results_table(records), end="")
    return 0


def _sweep_config_file(args: argparse.Namespace) -> dict[str, Any]:
    """Fill the sweep options the user did not type from ``--config`` (a sweep config, a sweep
    folder's sweep.json, or a run config, which becomes a sweep of its one run); returns the
    file's datasets, grid and task presets for the caller to merge with the typed ones. An
    agent module or env factory named in the file is refused unless typed too: names in files
    are never imported."""
    from rlu.commands._options import flat_values, typed_dests
    from rlu.training.config import RunSettings, read_config_file
    from rlu.training.prepare import TrainConfig
    from rlu.training.sweep import SweepConfig
    from rlu.types import FormatError, RluError

    try:
        data = read_config_file(args.config, SweepConfig)
    except FormatError as not_a_sweep:
        try:
            run = read_config_file(args.config, TrainConfig)
        except FormatError:
            raise not_a_sweep from None
        data = {
            "tasks": [run["task"]] if "task" in run else None,
            "agents": [run["agent"]] if "agent" in run else None,
            "seeds": [run["seed"]] if "seed" in run else None,
            "datasets": {run["task"]: run["dataset"]} if {"task", "dataset"} <= set(run) else {},
            "grid": {k: [v] for k, v in run.get("overrides", {}).items()} or None,
            "run": run.get("run", {}),
        }
        data = {k: v for k, v in data.items() if v is not None}
    typed = typed_dests(args.parser, args.argv)
    plain = {k: v for k, v in data.items() if k not in ("run", "datasets", "grid", "task_presets")}
    values = flat_values(SweepConfig, plain)
    values.update(flat_values(RunSettings, data.get("run", {})))
    for dest, value in values.items():
        if dest not in typed:
            setattr(args, dest, value)
    named = [a for a in (args.agents or []) if "." in a] if "agents" not in typed else []
    if named:
        raise RluError(
            f"{args.config}: field 'agents' names the agent module {named[0]!r}, and a module "
            f"named in a file is never imported; if you trust it, type it: --agents {named[0]}"
        )
    if "env" not in typed and args.env is not None:
        raise RluError(
            f"{args.config}: field 'env' names the env factory {args.env!r}, and a module "
            f"named in a file is never imported; if you trust it, type it: --env {args.env}"
        )
    return {k: data[k] for k in ("datasets", "grid", "task_presets") if data.get(k) is not None}


def _report(args: argparse.Namespace) -> int:
    from rlu.report import report

    paths = report(
        args.paths,
        args.out,
        fqe_steps=args.fqe_steps if args.fqe else None,
        device=args.device,
    )
    for p in paths:
        print(f"wrote {p}")
    return 0
