"""Sweeps: tasks x agents x the paper's hyper-parameter grids x seeds, one ``rlu.train`` run each.

Runs go to ``OUT/<task>/<agent>/<config>/seed_<s>``; a run whose ``result.json`` exists is
skipped, so running a sweep again finishes only what is missing (an interrupted run resumes from
its last checkpoint). Backends: a local process pool (default) or a Ray cluster
(``backend="ray"``; ``ray.init`` on ``ray_address``, or a local instance). Every run sets its own
seeds and torch thread count, so both backends give the same numbers. ``OUT/results.jsonl``
holds one record per finished run (task, agent, config, overrides, seed, score, run folder),
sorted, rewritten as each run finishes: ``rlu report`` reads a sweep in progress or interrupted.

Every run computes on ``SweepConfig.runtime`` (device, precision, data path). On Ray a run asks
for one CPU and ``gpus_per_run`` GPUs: a fraction packs several small runs onto one GPU (0.25:
four). The runtime and the GPU request may change when an interrupted sweep is continued.
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
from rlu.devices import Runtime, check_gpus_per_run, check_ray_gpus, ray_options
from rlu.types import DiscreteSpec, RluError, install_hint
from rlu.workers import die_with_parent


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
    runtime: Runtime = field(default_factory=Runtime)
    """Device, precision and data path of every run (``rlu.devices.Runtime``)."""
    gpus_per_run: float = 0.0
    """Ray backend: GPUs each run asks for (a fraction shares a GPU: 0.25 packs four runs)."""

    def __post_init__(self) -> None:
        check_gpus_per_run(self.gpus_per_run)

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
            runtime=config.runtime,
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
    if backend == "local" and config.gpus_per_run:
        raise RluError(
            "--gpus-per-run asks Ray for GPUs; use --backend ray, or drop it (local runs all see "
            "the machine's GPUs)"
        )
    if cfg_path.exists() and _what(runs.read_json(cfg_path)) != _what(config.to_json()):
        raise RluError(
            f"{cfg_path} was written by a different sweep configuration; use the same arguments "
            "to continue it or choose a new --out"
        )
    runs.write_json(cfg_path, config.to_json())
    specs = expand(config, out)
    paths = [p for p in sys.path if p and Path(p).is_dir()]
    finished = _Finished(out, len(specs), progress)
    if backend == "local":
        _run_local(specs, config, workers, paths, finished)
    elif backend == "ray":
        _run_ray(specs, config, ray_address, paths, finished)
    else:
        raise RluError(f"backend={backend!r}; use 'local' or 'ray'")
    finished.check()
    return finished.records


def _what(sweep_json: Mapping[str, Any]) -> dict[str, Any]:
    """A sweep config without how its runs compute (runtime, GPU request): what must match to
    continue a sweep in the same folder."""
    out = json.loads(json.dumps(sweep_json))
    out.pop("runtime", None)
    out.pop("gpus_per_run", None)
    return out


class _Finished:
    """The records of the finished runs, sorted; ``OUT/results.jsonl`` is rewritten after each
    one, so ``rlu report`` reads a sweep that is still running or was interrupted (its finished
    runs so far)."""

    def __init__(self, out: Path, total: int, progress: bool):
        self.out, self.total, self.progress = out, total, progress
        self.records: list[dict[str, Any]] = []
        self.failed: list[str] = []

    def fail(self, spec: RunSpec, error: BaseException) -> None:
        """A run that raised: the others go on; ``check`` names it at the end."""
        self.failed.append(f"{spec.run_dir}: {type(error).__name__}: {error}")
        if self.progress:
            print(f"[failed] {spec.task} {spec.agent} {spec.config} seed {spec.seed}: {error}",
                  file=sys.stderr)  # fmt: skip

    def check(self) -> None:
        if self.failed:
            raise RluError(
                f"{len(self.failed)} of {self.total} runs failed; the {len(self.records)} "
                f"finished are in {self.out / runs.RESULTS}; fix the cause and run the sweep "
                "again to retry only those:\n  " + "\n  ".join(self.failed)
            )

    def add(self, rec: dict[str, Any]) -> None:
        self.records.append(rec)
        self.records.sort(key=lambda r: (r["task"], r["agent"], r["config"], r["seed"]))
        runs.write_results(self.out, self.records)
        if self.progress:
            print(
                f"[{len(self.records)}/{self.total}] {rec['task']} {rec['agent']} {rec['config']} "
                f"seed {rec['seed']}: {rec['score']}",
                file=sys.stderr,
            )


def _run_local(specs, config, workers, paths, finished: _Finished) -> None:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    if workers <= 1:
        for r in specs:
            try:
                finished.add(run_one(r, config, paths))
            except Exception as e:  # one run's failure: the others still run
                finished.fail(r, e)
        return
    # spawn: a fresh interpreter per worker (torch and fork do not mix); workers die with the
    # driver, so a killed sweep leaves no run training on and holding its folder's lock
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(workers, ctx, die_with_parent, (os.getpid(),)) as pool:
        futures = {pool.submit(run_one, r, config, paths): r for r in specs}
        try:
            for f in as_completed(futures):
                try:
                    finished.add(f.result())
                except Exception as e:
                    finished.fail(futures[f], e)
        except BaseException:  # Ctrl-C: start no further run
            pool.shutdown(wait=False, cancel_futures=True)
            raise


def _run_ray(specs, config, address, paths, finished: _Finished) -> None:
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
        check_ray_gpus(ray, config.gpus_per_run, config.runtime.device)
        remote = ray.remote(**ray_options(config.gpus_per_run))(run_one)
        pending = {remote.remote(r, config, paths): r for r in specs}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                spec = pending.pop(ref)
                try:
                    finished.add(ray.get(ref))
                except Exception as e:
                    finished.fail(spec, e)
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
        # a run trained with --eval-every -1 has no score
        vals = [by_seed[s] for s in sorted(by_seed) if by_seed[s] is not None]
        scores = ", ".join(
            f"{s}: {'not evaluated' if v is None else format(v, '.6g')}"
            for s, v in sorted(by_seed.items())
        )
        mean = format(sum(vals) / len(vals), ".6g") if vals else "-"
        lines.append(f"| {task} | {agent} | {cfg} | {scores} | {mean} |")
    return "\n".join(lines) + "\n"
