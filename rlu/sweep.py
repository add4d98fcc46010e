"""Sweeps: tasks x agents x the paper's hyper-parameter grids x seeds, one ``rlu.train`` run each.

Runs go to ``OUT/<task>/<agent>/<config>/seed_<s>``; a run whose ``result.json`` exists is
skipped, so running a sweep again finishes only what is missing (an interrupted run resumes from
its last checkpoint). Backends: a local process pool (default) or a Ray cluster
(``backend="ray"``; ``ray.init`` on ``ray_address``, or a local instance). Every run sets its own
seeds and torch thread count, so both backends give the same numbers. ``OUT/results.jsonl``
holds one record per run (task, agent, config, overrides, seed, score, run folder), sorted.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rlu import runs
from rlu.types import DiscreteSpec, RluError, install_hint


@dataclass(frozen=True)
class SweepConfig:
    tasks: tuple[str, ...]
    agents: tuple[str, ...]
    datasets: Mapping[str, str]
    """Dataset path per task."""
    seeds: tuple[int, ...] = (0,)
    preset: str = "small"
    steps: int | None = None
    """Gradient steps per run (None: each agent config's ``num_steps``)."""
    grid: Mapping[str, Sequence[Any]] | None = None
    """Grid for every agent ({field: [values]}); None: each agent module's paper ``GRID``."""
    max_configs: int | None = None
    """Keep only the first N configurations of each grid (in grid order)."""
    eval_every: int = 0
    eval_episodes: int = 5
    eval_envs: int = 4
    eval_max_steps: int | None = None
    log_every: int = 100
    checkpoint_every: int = 1000
    env: str | None = None
    """Env factory 'module:function' (None: rlu.envs.make_env)."""
    challenge: str | None = None
    """RWRL: evaluate under this challenge (None: each dataset's own, from its provenance)."""
    task_presets: Mapping[str, str] = field(default_factory=dict)
    """Per-task preset replacing ``preset`` for the agents that have it: the paper's recurrent
    presets on the sequence locomotion tasks, ``{"locomotion/rodent_mazes": "paper_recurrent"}``."""
    torch_threads: int = 1
    """Threads per run: runs are the unit of parallelism."""

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["datasets"] = dict(self.datasets)
        d["task_presets"] = dict(self.task_presets)
        d["grid"] = None if self.grid is None else {k: list(v) for k, v in self.grid.items()}
        return d


@dataclass(frozen=True)
class RunSpec:
    task: str
    agent: str
    config: str
    """Label of the hyper-parameter setting, e.g. 'learning_rate=0.001'."""
    overrides: Mapping[str, Any] = field(default_factory=dict)
    seed: int = 0
    run_dir: str = ""
    preset: str = "small"
    """The agent preset of this run (the sweep's, or the task's where the agent has it)."""


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() or c in "-_.=," else "_" for c in text.replace("/", "__"))


def config_label(overrides: Mapping[str, Any]) -> str:
    return ",".join(f"{k}={overrides[k]}" for k in sorted(overrides)) or "default"


def agent_grid(agent: str, discrete: bool) -> dict[str, list[Any]]:
    from rlu.agents import agent_module

    return {k: list(v) for k, v in agent_module(agent, discrete).GRID.items()}


def agent_presets(agent: str, discrete: bool) -> tuple[str, ...]:
    from rlu.agents import agent_module

    return tuple(agent_module(agent, discrete).PRESETS)


def expand(config: SweepConfig, out: str | os.PathLike) -> list[RunSpec]:
    """Every run of the sweep, in (task, agent, config, seed) order."""
    from rlu.data import open_dataset

    specs = []
    for task in config.tasks:
        if task not in config.datasets:
            raise RluError(f"no dataset for task {task!r}; pass --dataset {task}=PATH")
        discrete = isinstance(open_dataset(config.datasets[task]).schema.action, DiscreteSpec)
        for agent in config.agents:
            preset = config.task_presets.get(task, config.preset)
            if preset not in agent_presets(agent, discrete):
                preset = config.preset  # e.g. no recurrent variant of this agent
            grid = dict(config.grid) if config.grid is not None else agent_grid(agent, discrete)
            keys = sorted(grid)
            settings = [
                dict(zip(keys, vals, strict=True))
                for vals in itertools.product(*(grid[k] for k in keys))
            ]
            if config.max_configs is not None:
                settings = settings[: config.max_configs]
            for overrides in settings:
                label = config_label(overrides)
                for seed in config.seeds:
                    run_dir = Path(out) / _slug(task) / _slug(agent) / _slug(label) / f"seed_{seed}"
                    specs.append(RunSpec(task, agent, label, overrides, seed, str(run_dir), preset))
    return specs


def run_one(spec: RunSpec, config: SweepConfig, sys_path: Sequence[str] = ()) -> dict[str, Any]:
    """Train one run (resuming or skipping it if it exists) and return its result record."""
    for p in sys_path:  # remote workers import test or user agent modules like the driver
        if p not in sys.path:
            sys.path.append(p)
    from rlu.train import TrainConfig, train

    run = Path(spec.run_dir)
    if (run / runs.RESULT).exists():
        result = runs.read_json(run / runs.RESULT)
    else:
        tc = TrainConfig(
            task=spec.task,
            agent=spec.agent,
            dataset=config.datasets[spec.task],
            preset=spec.preset,
            steps=config.steps,
            seed=spec.seed,
            overrides=dict(spec.overrides),
            eval_every=config.eval_every,
            eval_episodes=config.eval_episodes,
            eval_envs=config.eval_envs,
            eval_max_steps=config.eval_max_steps,
            log_every=config.log_every,
            checkpoint_every=config.checkpoint_every,
            env=config.env,
            challenge=config.challenge,
            torch_threads=config.torch_threads,
        )
        result = train(tc, run, resume=True)
    return {
        "task": spec.task,
        "agent": spec.agent,
        "config": spec.config,
        "overrides": dict(spec.overrides),
        "seed": spec.seed,
        "preset": spec.preset,
        "env_settings": result["env_settings"],
        "score": result["score"],
        "returns": (result.get("final_eval") or {}).get("returns"),
        "run": str(run),
    }


def sweep(
    config: SweepConfig,
    out: str | os.PathLike,
    backend: str = "local",
    workers: int = 2,
    ray_address: str | None = None,
    progress: bool = False,
) -> list[dict[str, Any]]:
    """Run every missing run of the sweep; return (and write to OUT/results.jsonl) all records."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg_path = out / runs.SWEEP_CONFIG
    wanted = json.loads(json.dumps(config.to_json()))
    if cfg_path.exists() and runs.read_json(cfg_path) != wanted:
        raise RluError(
            f"{cfg_path} was written by a different sweep configuration; use the same arguments "
            "to continue it or choose a new --out"
        )
    runs.write_json(cfg_path, config.to_json())
    specs = expand(config, out)
    paths = [p for p in sys.path if p and Path(p).is_dir()]
    if backend == "local":
        records = _run_local(specs, config, workers, paths, progress)
    elif backend == "ray":
        records = _run_ray(specs, config, ray_address, paths, progress)
    else:
        raise RluError(f"backend={backend!r}; use 'local' or 'ray'")
    records.sort(key=lambda r: (r["task"], r["agent"], r["config"], r["seed"]))
    runs.write_results(out, records)
    return records


def _note(progress: bool, done: int, total: int, rec: dict[str, Any]) -> None:
    if progress:
        print(
            f"[{done}/{total}] {rec['task']} {rec['agent']} {rec['config']} seed {rec['seed']}: "
            f"{rec['score']}",
            file=sys.stderr,
        )


def _run_local(specs, config, workers, paths, progress) -> list[dict[str, Any]]:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    if workers <= 1:
        out = []
        for i, r in enumerate(specs):
            out.append(run_one(r, config, paths))
            _note(progress, i + 1, len(specs), out[-1])
        return out
    # spawn: a fresh interpreter per worker (torch and fork do not mix)
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
        futures = [pool.submit(run_one, r, config, paths) for r in specs]
        records = []
        for i, f in enumerate(as_completed(futures)):
            records.append(f.result())
            _note(progress, i + 1, len(specs), records[-1])
    return records


def _run_ray(specs, config, address, paths, progress) -> list[dict[str, Any]]:
    try:
        import ray
    except ImportError:
        raise RluError(f"the Ray backend needs ray: {install_hint('distributed')}") from None
    started = False
    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(
                num_cpus=max(1, os.cpu_count() or 1), include_dashboard=False, log_to_driver=False
            )
        started = True
    try:
        remote = ray.remote(num_cpus=1)(run_one)
        pending = {remote.remote(r, config, paths): r for r in specs}
        records = []
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                pending.pop(ref)
                records.append(ray.get(ref))
                _note(progress, len(records), len(specs), records[-1])
        return records
    finally:
        if started:
            ray.shutdown()


def results_table(records: Sequence[Mapping[str, Any]]) -> str:
    """Markdown table of every (task, agent, config): per-seed scores and their mean."""
    from collections import defaultdict

    groups: dict[tuple[str, str, str], dict[int, float]] = defaultdict(dict)
    for r in records:
        groups[(r["task"], r["agent"], r["config"])][int(r["seed"])] = r["score"]
    lines = ["| task | agent | config | scores by seed | mean |", "|---|---|---|---|---|"]
    for (task, agent, cfg), by_seed in sorted(groups.items()):
        vals = [by_seed[s] for s in sorted(by_seed)]
        scores = ", ".join(f"{s}: {by_seed[s]:.6g}" for s in sorted(by_seed))
        lines.append(f"| {task} | {agent} | {cfg} | {scores} | {sum(vals) / len(vals):.6g} |")
    return "\n".join(lines) + "\n"
