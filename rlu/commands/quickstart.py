"""``rlu quickstart``: the README's main job, a small benchmark end to end on the bundled data.

On the bundled ``control_suite/cartpole_swingup`` dataset (40 episodes made by ``rlu generate``,
shipped in the package): validate it, evaluate the uniform random policy, train BC and two
offline RL agents (D4PG run offline, the paper's; IQL, a newer one) with their ``small``
presets, one process per core, evaluate each greedy policy in the env, and print the results
beside the dataset's return statistics and BC's return. Writes
``OUT/report.md``, ``OUT/results.json`` and ``OUT/quickstart.png`` (each policy's mean return
beside the dataset's episode-return distribution; needs matplotlib, the ``report`` extra); each
agent's run folder (config, metrics, evaluations, checkpoints) is ``OUT/<agent>``.
"""

from __future__ import annotations

import argparse

from rlu.commands.train import add_device_option

DEFAULT_AGENTS = ("bc", "d4pg", "iql")
# Enough for offline RL to pull away from BC on the bundled data (D4PG: 195 at 10,000 steps,
# 761 at 20,000; BC 176 and 218), within the quick start's 10 minutes on 2 cores (BCQ, 33 ms
# per update there, would not fit: IQL stands beside D4PG).
DEFAULT_STEPS = 20_000


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("quickstart", help="train BC + 2 offline RL agents on the bundled data")
    p.add_argument("--out", default="runs/quickstart", help="working directory (replaced)")
    p.add_argument("--agents", nargs="+", default=list(DEFAULT_AGENTS))
    p.add_argument("--steps", type=int, default=DEFAULT_STEPS, help="gradient steps per agent")
    p.add_argument("--eval-episodes", type=int, default=5, help="env episodes per policy")
    p.add_argument("--dataset", default=None, help="another rlu dataset of the same task")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch threads per agent")
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help="agents trained at once, one process each (default: one per core); the numbers "
        "do not depend on it",
    )
    add_device_option(p)
    p.set_defaults(func=_run)


def _row(name: str, returns) -> dict:
    import numpy as np

    r = np.asarray(returns, np.float64)
    return {"policy": name, "mean": float(r.mean()), "std": float(r.std()), "returns": r.tolist()}


def _train_all(configs: dict, out, workers: int, t0: float) -> dict[str, dict]:
    """Train every agent (one run folder each under ``out``); ``workers`` > 1 trains them at
    once in spawned processes. Each run is a function of its config alone, so the results do
    not depend on ``workers``."""
    import time

    from rlu.train import train

    def done(agent: str, result: dict) -> None:
        print(f"  {agent} ({result['steps']} steps, small preset): "
              f"{result['final_eval']['mean']:.1f}  ({time.perf_counter() - t0:.0f}s)")  # fmt: skip

    results = {}
    if workers <= 1:
        for agent, cfg in configs.items():
            results[agent] = train(cfg, out / agent, progress=True)
            done(agent, results[agent])
        return results
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    print(f"  training {', '.join(configs)} in {workers} processes")
    # spawn: a fresh interpreter per worker (torch and fork do not mix)
    with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
        futures = {pool.submit(train, cfg, out / agent): agent for agent, cfg in configs.items()}
        for f in as_completed(futures):
            results[futures[f]] = f.result()
            done(futures[f], results[futures[f]])
    return results


PAPER_CARTPOLE = "the paper on this task: D4PG 856, BRAC 869, RABM 798 against BC 386"


def _against_bc(rows: list[dict], task_id: str) -> list[str]:
    """The paper's first control-suite comparison: offline RL against BC (none without BC)."""
    bc = next((r for r in rows if r["policy"] == "bc"), None)
    others = [r for r in rows if r["policy"] not in ("random", "bc")]
    if bc is None or not others or bc["mean"] <= 0:
        return []
    best = max(others, key=lambda r: r["mean"])
    return [
        f"Best offline RL agent: {best['policy']}, {best['mean'] / bc['mean']:.2f} times BC's "
        "return"
        + (f" ({PAPER_CARTPOLE})." if task_id == "control_suite/cartpole_swingup" else "."),
        "",
    ]


def _figure(rows, dataset_returns, task_id: str, path):
    """Draw OUT/quickstart.png; None (and a note) without matplotlib."""
    import importlib.util

    from rlu.types import install_hint

    if importlib.util.find_spec("matplotlib") is None:
        print(f"  (no figure: it needs matplotlib, {install_hint('report')})")
        return None
    from rlu.evaluation.report.render import pyplot, quickstart_figure

    plt = pyplot()
    title = f"rlu quickstart: {task_id}, policies beside the dataset's episode returns"
    fig = quickstart_figure(rows, dataset_returns, title, plt)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _run(args: argparse.Namespace) -> int:
    import importlib.util
    import json
    import os
    import shutil
    import time
    from pathlib import Path

    import numpy as np

    from rlu.types import RluError, derive_seed, install_hint

    missing = [m for m in ("torch", "dm_control") if importlib.util.find_spec(m) is None]
    if missing:
        raise RluError(
            f"rlu quickstart trains agents (torch) in the control suite (dm_control); "
            f"{', '.join(missing)} missing: {install_hint('control', 'agents')}"
        )
    if args.workers is not None and args.workers < 1:
        raise RluError(f"--workers {args.workers}: give at least 1 process")
    from rlu.data import open_dataset
    from rlu.data.validate import validate
    from rlu.devices import Runtime
    from rlu.evaluation.rollout import evaluate, task_env_factory
    from rlu.generate.recipe import bundled_dataset
    from rlu.train import TrainConfig

    t0 = time.perf_counter()
    path = Path(args.dataset) if args.dataset else bundled_dataset()
    ds = open_dataset(path)
    task_id = ds.schema.task_id
    out = Path(args.out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    report = validate(path)
    stats = ds.info()["returns"]
    command = ds.manifest["provenance"].get("command", "?")
    print(f"dataset {task_id}: {path}")
    print(f"  made by: {command}")
    print(
        f"  {stats['episodes']} episodes, {ds.num_steps} steps, return mean {stats['mean']:.1f} "
        f"p90 {stats['p90']:.1f} max {stats['max']:.1f}; validate: "
        f"{'valid' if report.ok else report.problems}"
    )

    runtime = Runtime(device=args.device)
    print(f"  device: {runtime.resolve().device}")

    env_fn = task_env_factory(task_id)
    action_shape = ds.schema.action.shape
    rng = np.random.default_rng(args.seed)

    def random_policy(obs, is_first):
        n = len(next(iter(obs.values()))) if isinstance(obs, dict) else len(obs)
        return rng.uniform(-1.0, 1.0, (n, *action_shape)).astype(np.float32)

    # the episodes each agent's final evaluation plays (rlu.train seeds it with stream `steps`)
    eval_seed = derive_seed(args.seed, args.steps)
    rows = [_row("random", evaluate(random_policy, env_fn, args.eval_episodes, eval_seed).returns)]
    print(f"  random policy: {rows[0]['mean']:.1f}  ({time.perf_counter() - t0:.0f}s)")
    configs = {
        agent: TrainConfig(
            task=task_id,
            agent=agent,
            dataset=str(path),
            preset="small",
            steps=args.steps,
            seed=args.seed,
            eval_every=0,
            eval_episodes=args.eval_episodes,
            checkpoint_every=args.steps,
            keep_checkpoints=1,
            torch_threads=args.threads,
            runtime=runtime,
        )
        for agent in args.agents
    }
    workers = min(len(configs), args.workers or os.cpu_count() or 1)
    results = _train_all(configs, out, workers, t0)
    for agent in args.agents:
        rows.append(_row(agent, results[agent]["final_eval"]["returns"]))

    lines = [
        f"# rlu quickstart: {task_id}",
        "",
        f"Dataset: `{path}` ({stats['episodes']} episodes, made by `{command}`).",
        f"Each agent: {args.steps} gradient steps, small preset, seed {args.seed}; every policy "
        f"evaluated on {args.eval_episodes} env episodes.",
        "",
        "| policy | mean return | std | / dataset mean | beats the data |",
        "|---|---:|---:|---:|---|",
    ]
    for r in rows:
        beats = "yes" if r["mean"] > stats["mean"] else "no"
        lines.append(f"| {r['policy']} | {r['mean']:.1f} | {r['std']:.1f} | "
                     f"{r['mean'] / stats['mean']:.2f} | {beats} |")  # fmt: skip
    lines += [
        f"| *dataset* | {stats['mean']:.1f} | {stats['std']:.1f} | 1.00 | |",
        "",
        *_against_bc(rows, task_id),
        f"Dataset returns: mean {stats['mean']:.1f}, p90 {stats['p90']:.1f}, "
        f"min {stats['min']:.1f}, max {stats['max']:.1f}.",
        "",
    ]
    figure = _figure(rows, ds.episode_returns(), task_id, out / "quickstart.png")
    if figure is not None:
        lines += [f"![policies beside the dataset's returns]({figure.name})", ""]
    text = "\n".join(lines)
    (out / "report.md").write_text(text)
    result = {"task": task_id, "dataset": str(path), "dataset_returns": stats, "policies": rows,
              "steps": args.steps, "seconds": time.perf_counter() - t0}  # fmt: skip
    (out / "results.json").write_text(json.dumps(result, indent=1))
    print()
    print(text)
    beat = [r["policy"] for r in rows[1:] if r["mean"] > rows[0]["mean"]]
    print(f"beat the random policy: {', '.join(beat) or 'none'}; "
          f"report: {out / 'report.md'}; {time.perf_counter() - t0:.0f}s")  # fmt: skip
    return 0 if report.ok else 1
