"""``rlu quickstart``: the README's main job, a small benchmark end to end on the bundled data.

On the bundled ``control_suite/cartpole_swingup`` dataset (40 episodes made by ``rlu generate``,
shipped in the package): validate it, evaluate the uniform random policy, then a sweep of BC and
two offline RL agents (D4PG run offline, the paper's; IQL, a newer one) with their ``small``
presets, one process per core, and the quick-start report (``rlu.report.quickstart``):
each greedy policy's return beside the dataset's, in ``OUT/report.md``, ``OUT/results.json`` and
``OUT/quickstart.png`` (with matplotlib, the ``report`` extra). The sweep folder is
``OUT/sweep``, one run folder per agent.

``--out`` is replaced: only a folder an earlier quick start wrote (it holds ``results.json``),
never one holding the dataset, and only after every argument has been checked.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rlu.commands.train import add_backend_options, add_device_option

DEFAULT_AGENTS = ("bc", "d4pg", "iql")
# Enough for offline RL to pull away from BC on the bundled data within the quick start's 10
# minutes on 2 cores (the measurements: README.md and bench/README.md).
DEFAULT_STEPS = 20_000


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("quickstart", help="train BC + 2 offline RL agents on the bundled data")
    p.add_argument(
        "--out",
        default="runs/quickstart",
        help="working folder (default: runs/quickstart; an earlier quick start's is replaced)",
    )
    p.add_argument(
        "--agents",
        nargs="+",
        default=list(DEFAULT_AGENTS),
        help=f"agents to train (default: {' '.join(DEFAULT_AGENTS)})",
    )
    p.add_argument(
        "--steps",
        type=_count,
        default=DEFAULT_STEPS,
        metavar="N",
        help=f"learner steps per agent (default: {DEFAULT_STEPS:,})",
    )
    p.add_argument(
        "--eval-episodes",
        type=_count,
        default=5,
        metavar="N",
        help="env episodes per policy (default: 5)",
    )
    p.add_argument(
        "--dataset",
        default=None,
        help="another dataset of a control-suite task, as rlu.load_dataset names it (a task id, "
        "a TFDS name or a folder; default: the bundled one)",
    )
    p.add_argument("--seed", type=_seed, default=0, help="seed of every run (default: 0)")
    p.add_argument(
        "--threads",
        type=_count,
        default=1,
        metavar="N",
        help="torch threads per agent (default: 1)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress of the runs (stderr)")
    add_backend_options(p)
    add_device_option(p)
    p.set_defaults(func=_run)


def _count(text: str) -> int:
    from rlu.commands._options import checked

    return checked(int, {"min": 1}, "this option")(text)


def _seed(text: str) -> int:
    from rlu.commands._options import checked

    return checked(int, {"min": 0}, "--seed")(text)


def _run(args: argparse.Namespace) -> int:
    import time

    from rlu.devices import Runtime
    from rlu.report.quickstart import policy_row, write_quickstart_report
    from rlu.training.sweep import sweep

    t0 = time.perf_counter()
    ds, backend, out, valid = _checked(args)
    path = Path(ds.path)
    task_id = ds.schema.task_id
    runtime = Runtime(device=args.device)
    print(f"  device: {runtime.resolve().device}")
    rows = [policy_row("random", _random_returns(ds, args))]
    print(f"  random policy: {rows[0]['mean']:.1f}  ({time.perf_counter() - t0:.0f}s)")
    print(
        f"  training {', '.join(args.agents)} ({args.steps:,} steps each, small preset) in "
        f"{backend.workers} process(es)"
    )
    config = _sweep_config(args, ds, runtime)
    records = sweep(config, out / "sweep", backend, progress=not args.quiet)
    by_agent = {r["agent"]: r for r in records}
    for agent in args.agents:
        r = by_agent[agent]
        made = {k: r[k] for k in ("preset", "steps", "eval_episodes")}
        rows.append(policy_row(agent, r["returns"], **made))
    command = ds.manifest["provenance"].get("command", "?")
    text = write_quickstart_report(
        out, task_id, path, command, ds.episode_returns(), rows, time.perf_counter() - t0
    )
    print()
    print(text)
    beat = [r["policy"] for r in rows[1:] if r["mean"] > rows[0]["mean"]]
    print(
        f"beat the random policy: {', '.join(beat) or 'none'}; "
        f"report: {out / 'report.md'}; {time.perf_counter() - t0:.0f}s"
    )
    return 0 if valid else 1


def _checked(args: argparse.Namespace) -> tuple[Any, Any, Path, bool]:
    """(dataset, backend, --out, whether the data are valid), every argument checked before
    anything on disk is touched; then --out is replaced and the dataset described."""
    import importlib.util
    import shutil

    from rlu.system import install_hint
    from rlu.types import DiscreteSpec, RluError

    missing = [m for m in ("torch", "dm_control") if importlib.util.find_spec(m) is None]
    if missing:
        raise RluError(
            f"rlu quickstart trains agents (torch) in the control suite (dm_control); "
            f"{', '.join(missing)} missing: {install_hint('control', 'agents')}"
        )
    from rlu.agents import agent_module
    from rlu.commands.train import backend_from_args
    from rlu.data import load_dataset, open_dataset
    from rlu.data.bundled import bundled_dataset, bundled_tasks
    from rlu.data.validate import validate
    from rlu.files import check_output
    from rlu.report.quickstart import MARKER

    ds = load_dataset(args.dataset) if args.dataset else open_dataset(bundled_dataset())
    path = Path(ds.path)
    task_id = ds.schema.task_id
    homes = sorted({t.partition("/")[0] for t in bundled_tasks()})
    if not task_id or task_id.partition("/")[0] not in homes:
        raise RluError(
            f"{path}: a dataset of task {task_id!r}; the quick start runs on data of the "
            f"bundled dataset's domain ({', '.join(homes)}; rlu train and rlu sweep run on any)"
        )
    for agent in args.agents:
        agent_module(agent, isinstance(ds.schema.action, DiscreteSpec))  # unknown: fails here
    backend = backend_from_args(args, jobs=len(args.agents))
    out = check_output(args.out, [path], MARKER, "quick-start folder")
    report = validate(path)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)

    stats = ds.info()["returns"]
    print(f"dataset {task_id}: {path}")
    print(f"  made by: {ds.manifest['provenance'].get('command', '?')}")
    print(
        f"  {stats['episodes']} episodes, {ds.num_steps} steps, return mean {stats['mean']:.1f} "
        f"p90 {stats['p90']:.1f} max {stats['max']:.1f}; validate: "
        f"{'valid' if report.ok else report.problems}"
    )
    return ds, backend, out, report.ok


def _random_returns(ds: Any, args: argparse.Namespace) -> Any:
    """The uniform random policy's returns, on the episodes each agent's final evaluation plays
    (``rlu.training.train`` seeds it with stream ``steps``)."""
    import numpy as np

    from rlu.evaluation.rollout import evaluate, task_env_factory
    from rlu.seeds import derive_seed

    action_shape = ds.schema.action.shape
    rng = np.random.default_rng(args.seed)

    def random_policy(observation: Any, is_first: np.ndarray, reward: np.ndarray) -> np.ndarray:
        obs = observation
        n = len(next(iter(obs.values()))) if isinstance(obs, dict) else len(obs)
        return rng.uniform(-1.0, 1.0, (n, *action_shape)).astype(np.float32)

    env_fn = task_env_factory(ds.schema.task_id)
    seed = derive_seed(args.seed, args.steps)
    return evaluate(random_policy, env_fn, args.eval_episodes, seed).returns


def _sweep_config(args: argparse.Namespace, ds: Any, runtime: Any) -> Any:
    """The sweep of the agents' small presets on the dataset, one configuration each."""
    from rlu.training.config import RunSettings
    from rlu.training.sweep import SweepConfig

    task_id = ds.schema.task_id
    return SweepConfig(
        tasks=(task_id,),
        agents=tuple(args.agents),
        datasets={task_id: str(ds.path)},
        seeds=(args.seed,),
        grid={},  # each agent's small preset as it is: one configuration
        run=RunSettings(
            preset="small",
            steps=args.steps,
            eval_every=0,
            eval_episodes=args.eval_episodes,
            checkpoint_every=args.steps,
            keep_checkpoints=1,
            torch_threads=args.threads,
            runtime=runtime,
        ),
    )
