"""Sweeps: tasks x agents x the paper's hyper-parameter grids x seeds, one ``rlu.training.train``
run each.

Runs go to ``OUT/<task>/<agent>/<config>/seed_<s>``; a run whose ``result.json`` exists is
skipped, so running a sweep again finishes only what is missing (an interrupted run resumes from
its last checkpoint). Backends: a local process pool (default) or a Ray cluster
(``Backend("ray")``; ``ray.init`` on its address, or a local instance). Every run sets its own
seeds and torch thread count, so both backends give the same numbers. ``OUT/results.jsonl``
holds one record per finished run (task, agent, config, overrides, seed, score, run folder),
sorted, rewritten as each run finishes: ``rlu report`` reads a sweep in progress or interrupted.

Every run is run by ``SweepConfig.run`` (an ``rlu.training.config.RunSettings``: preset, budget,
evaluation, checkpoints; its runtime: device, precision, data path); each run's record in
results.jsonl says what produced its score (preset, steps, data source, evaluation episodes).
Runs are spread by the one runner (``rlu.workers.run_jobs``). On Ray a run asks for one CPU and
``Backend.gpus_per_job`` GPUs: a fraction packs several small runs onto one GPU (0.25: four);
the runtime and the GPU request may change when an interrupted sweep is continued.
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

from rlu.devices import check_ray_gpus
from rlu.files import Checked, bounds, check_output, make_folder, shape_of
from rlu.training import runs
from rlu.training.config import RunSettings
from rlu.training.loggers import LOGGERS, check_logger_settings
from rlu.types import ConfigError, DiscreteSpec, RluError
from rlu.workers import Backend, run_jobs


@dataclass(frozen=True)
class SweepConfig(Checked):
    """Tasks x agents x grids x seeds, every run run by ``run`` (the template)."""

    tasks: tuple[str, ...]
    """Task ids, e.g. control_suite/cartpole_swingup atari/Pong."""
    agents: tuple[str, ...]
    """Agent names (bc, d4pg, ...) or agent module paths you typed."""
    datasets: Mapping[str, str] = field(default_factory=dict)
    """The data of each task, as rlu.load_dataset names it (a task id, a TFDS name or a folder;
    a task left out trains on its own id's dataset), stored as the resolved folder: a sweep
    folder reports from anywhere."""
    seeds: tuple[int, ...] = field(
        default=(0,), metadata=bounds(min=0, max=2**63 - 1, min_len=1, max_len=10_000)
    )
    """Seeds of every configuration."""
    grid: Mapping[str, Sequence[Any]] | None = None
    """Grid for every agent ({field: [values]}); None: each agent module's paper GRID."""
    max_configs: int | None = field(default=None, metadata=bounds(min=1, max=10**6))
    """Keep only the first N configurations of each grid (in grid order)."""
    task_presets: Mapping[str, str] = field(default_factory=dict)
    """Per-task preset replacing ``run.preset`` for the agents that have it: the paper's
    recurrent presets on the sequence locomotion tasks, {"locomotion/rodent_mazes":
    "paper_recurrent"}."""
    run: RunSettings = field(default_factory=RunSettings)
    """How every run is run (preset, budget, evaluation, checkpoints, runtime)."""
    loggers: tuple[str, ...] = field(
        default=(), metadata=bounds(choices=LOGGERS, flag="--log-to", metavar="LOGGER")
    )
    """Where every run also logs its metrics (rlu train --log-to: csv, tensorboard, wandb);
    loggers change nothing a run computes, so a sweep may be continued with others."""

    @classmethod
    def from_file(cls, path: str | os.PathLike, **fields: Any) -> SweepConfig:
        """The sweep config of a JSON or YAML file with SweepConfig's fields (``run:`` holding
        RunSettings'), or a sweep folder's sweep.json; ``fields`` fill or replace top-level
        fields. A module path in the file (a dotted agent, ``run.env``) is refused unless
        ``fields`` names that field (names in files are never imported)."""
        from rlu.training.config import config_from_file

        return config_from_file(cls, os.fspath(path), fields)

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


config_label = runs.config_label


def agent_grid(agent: str, discrete: bool) -> dict[str, list[Any]]:
    from rlu.agents import agent_module

    return {k: list(v) for k, v in agent_module(agent, discrete).GRID.items()}


def agent_presets(agent: str, discrete: bool) -> tuple[str, ...]:
    from rlu.agents import agent_module

    return tuple(agent_module(agent, discrete).PRESETS)


def expand(config: SweepConfig, out: str | os.PathLike) -> list[RunSpec]:
    """Every run of the sweep, in (task, agent, config, seed) order. A module path among the
    agents (or the env factory) is imported here: the config came from code or the command
    line, never from a file."""
    from rlu.agents import make_config
    from rlu.data import open_dataset
    from rlu.training.prepare import trust

    for agent in config.agents:
        trust(agent, config.run.env)

    specs = []
    for task in config.tasks:
        if task not in config.datasets:
            raise RluError(f"no dataset for task {task!r}; pass --dataset {task}=PATH")
        discrete = isinstance(open_dataset(config.datasets[task]).schema.action, DiscreteSpec)
        for agent in config.agents:
            preset = config.task_presets.get(task, config.run.preset)
            if preset not in agent_presets(agent, discrete):
                preset = config.run.preset  # e.g. no recurrent variant of this agent
            grid = dict(config.grid) if config.grid is not None else agent_grid(agent, discrete)
            keys = sorted(grid)
            settings = [
                dict(zip(keys, vals, strict=True))
                for vals in itertools.product(*(grid[k] for k in keys))
            ]
            if config.max_configs is not None:
                settings = settings[: config.max_configs]
            for overrides in settings:
                try:  # every grid point's config checked before the sweep folder is made
                    make_config(agent, discrete, preset, **overrides)
                except ConfigError as e:
                    raise ConfigError(f"sweep grid of {agent} on {task}: {e}") from None
                label = config_label(overrides)
                for seed in config.seeds:
                    run_dir = Path(out) / _slug(task) / _slug(agent) / _slug(label) / f"seed_{seed}"
                    specs.append(RunSpec(task, agent, label, overrides, seed, str(run_dir), preset))
    return specs


def run_one(spec: RunSpec, config: SweepConfig) -> dict[str, Any]:
    """Train one run (resuming or skipping it if it exists) and return its result record; its
    steps go to the sweep's display as they are done (``rlu.progress.Relay``)."""
    from rlu.progress import Relay
    from rlu.training.prepare import TrainConfig
    from rlu.training.train import train

    run = Path(spec.run_dir)
    if (run / runs.RESULT).exists():
        result = runs.read_result(run)
    else:
        tc = TrainConfig(
            task=spec.task,
            agent=spec.agent,
            dataset=config.datasets[spec.task],
            seed=spec.seed,
            overrides=dict(spec.overrides),
            run=dataclasses.replace(config.run, preset=spec.preset),
        )
        result = train(tc, run, resume=True, progress=Relay(spec.run_dir), loggers=config.loggers)
    return {
        "task": spec.task,
        "agent": spec.agent,
        "config": spec.config,
        "overrides": dict(spec.overrides),
        "seed": spec.seed,
        "preset": spec.preset,
        "steps": result["steps"],
        "pretrain_steps": result.get("pretrain_steps", 0),
        "eval_episodes": result.get("eval_episodes", config.run.eval_episodes),
        "data": result.get("data", {"source": "unknown"}),
        "env_settings": result.get("env_settings", {}),
        "score": result["score"],
        "returns": (result.get("final_eval") or {}).get("returns"),
        "run": str(run),
    }


def plan(config: SweepConfig, specs: Sequence[RunSpec]) -> list[str]:
    """What the sweep will run, in lines: per task and agent, its preset, the grid (and whether
    it is the agent's paper grid) and the seeds; and how many runs in all."""
    from collections import Counter

    lines = []
    per = Counter((s.task, s.agent) for s in specs)
    seen = set()
    for s in specs:
        if (s.task, s.agent) in seen:
            continue
        seen.add((s.task, s.agent))
        configs = sorted({x.config for x in specs if (x.task, x.agent) == (s.task, s.agent)})
        source = "--grid" if config.grid is not None else f"{s.agent}'s paper grid"
        shown = ", ".join(configs[:4]) + (f" ... ({len(configs)})" if len(configs) > 4 else "")
        lines.append(
            f"  {s.task} x {s.agent} ({s.preset} preset): {len(configs)} config(s) from "
            f"{source} [{shown}] x {len(config.seeds)} seed(s) = {per[(s.task, s.agent)]} runs"
        )
    lines.append(f"  {len(specs)} runs in all")
    return lines


def sweep(
    config: SweepConfig,
    out: str | os.PathLike,
    backend: Backend | None = None,
    progress: bool = False,
) -> list[dict[str, Any]]:
    """Run every missing run of the sweep; return (and write to OUT/results.jsonl) all records.

    One process per sweep folder: a second ``sweep`` into the same ``out`` fails at once with
    "in use by PID N" while the first lives (its runs' folders are locked too)."""
    from rlu.locks import OutputLock

    out = Path(out)
    where = backend or Backend()
    config = dataclasses.replace(config, datasets=resolve_datasets(config))
    check_output(out, list(config.datasets.values()), runs.SWEEP_CONFIG, "sweep folder")
    unknown = [n for n in config.loggers if n not in LOGGERS]
    if unknown:
        raise RluError(f"logger {unknown[0]!r}; loggers are {', '.join(LOGGERS)}")
    check_logger_settings(config.loggers)  # an unknown WANDB_MODE, no W&B key: before the folder
    where.reach()  # a Ray cluster that does not answer: refused before the folder
    with OutputLock(out, "sweep folder"):
        cfg_path = out / runs.SWEEP_CONFIG
        if cfg_path.exists():
            old = runs.load_sweep_config(out, shape_of(SweepConfig))
            if _what(old) != _what(config.to_json()):
                raise RluError(
                    f"{cfg_path} was written by a different sweep configuration; use the same "
                    "arguments to continue it or choose a new --out"
                )
        specs = expand(config, out)
        make_folder(out)
        runs.write_json(cfg_path, config.to_json())
        todo = [s for s in specs if not (Path(s.run_dir) / runs.RESULT).exists()]
        if progress:
            print(f"rlu sweep: {out}", file=sys.stderr)
            for line in plan(config, specs):
                print(line, file=sys.stderr)
            if len(todo) < len(specs):
                print(
                    f"  {len(specs) - len(todo)} already finished (skipped), {len(todo)} to run",
                    file=sys.stderr,
                )
        finished = _Finished(out, len(specs), progress, len(todo), config.run.steps)
        for spec in specs:
            if spec not in todo:
                finished.add(run_one(spec, config), quiet=True)
        check = None
        if where.kind == "ray":

            def check(ray: Any) -> None:
                check_ray_gpus(ray, where.gpus_per_job, config.run.runtime.device)

        try:
            run_jobs(
                run_one,
                [(spec, config) for spec in todo],
                where,
                on_result=lambda i, rec: finished.add(rec),
                on_error=lambda i, e: finished.fail(todo[i], e),
                on_message=finished.bar.message,
                ray_check=check,
            )
        finally:
            finished.bar.close(failed=bool(finished.failed))
        finished.check()
        return finished.records


def resolve_datasets(config: SweepConfig) -> dict[str, str]:
    """The dataset folder of every task of ``config``: what ``rlu.load_dataset`` makes of its
    ``datasets`` entry (a task without one: of the task id itself), resolved."""
    from rlu.data import load_dataset

    unknown = sorted(set(config.datasets) - set(config.tasks))
    if unknown:
        raise RluError(
            f"a dataset is given for {unknown[0]!r}, which is not one of the sweep's tasks "
            f"({', '.join(config.tasks)}); add it to the tasks or drop its dataset"
        )
    return {
        t: str(Path(load_dataset(config.datasets.get(t, t)).path).resolve()) for t in config.tasks
    }


def _what(sweep_json: Mapping[str, Any]) -> dict[str, Any]:
    """A sweep config without how its runs compute (runtime) and where they also log: what
    must match to continue a sweep in the same folder."""
    out = json.loads(json.dumps(sweep_json))
    out.get("run", {}).pop("runtime", None)
    out.pop("loggers", None)
    return out


class _Finished:
    """The records of the finished runs, sorted; ``OUT/results.jsonl`` is rewritten after each
    one, so ``rlu report`` reads a sweep that is still running or was interrupted (its finished
    runs so far)."""

    def __init__(self, out: Path, total: int, progress: bool, todo: int, steps: int | None):
        from rlu.progress import Tally

        self.out, self.total, self.progress = out, total, progress
        self.records: list[dict[str, Any]] = []
        self.failed: list[str] = []
        # the learner steps of every run to do, as their workers report them
        self.bar = Tally(todo, "sweep", "steps", estimate=steps, quiet=not progress)

    def fail(self, spec: RunSpec, error: BaseException) -> None:
        """A run that raised: the others go on; ``check`` names it at the end."""
        why = (str(error).splitlines() or [""])[0]
        self.failed.append(f"{spec.run_dir}: {type(error).__name__}: {why}")
        self.bar.note(f"[failed] {spec.task} {spec.agent} {spec.config} seed {spec.seed}: {why}")
        self.bar.drop(spec.run_dir)
        self.bar.set_postfix(failed=len(self.failed))

    def check(self) -> None:
        if self.failed:
            raise RluError(
                f"{len(self.failed)} of {self.total} runs failed (first: {self.failed[0]}); the "
                f"{len(self.records)} finished are in {self.out / runs.RESULTS}; fix the cause "
                "and run the sweep again to retry only those"
            )

    def add(self, rec: dict[str, Any], quiet: bool = False) -> None:
        self.records.append(rec)
        self.records.sort(key=lambda r: (r["task"], r["agent"], r["config"], r["seed"]))
        runs.write_results(self.out, self.records)
        if not quiet:
            score = "not evaluated" if rec["score"] is None else f"{rec['score']:.1f}"
            self.bar.note(
                f"{rec['task']} {rec['agent']} {rec['config']} seed {rec['seed']}: "
                f"{score} ({rec['preset']} preset, {rec['steps']:,} steps)"
            )
            self.bar.finish(rec["run"])


def results_table(records: Sequence[Mapping[str, Any]]) -> str:
    """Markdown table of every (task, agent, config): preset and steps, per-seed scores and
    their mean."""
    from collections import defaultdict

    groups: dict[tuple[str, str, str], dict[int, float]] = defaultdict(dict)
    made: dict[tuple[str, str, str], str] = {}
    for r in records:
        key = (r["task"], r["agent"], r["config"])
        groups[key][int(r["seed"])] = r["score"]
        made[key] = f"{r.get('preset', '?')}, {r.get('steps', '?')} steps"
    lines = [
        "| task | agent | config | preset, steps | scores by seed | mean |",
        "|---|---|---|---|---|---|",
    ]
    for (task, agent, cfg), by_seed in sorted(groups.items()):
        # a run trained with --eval-every -1 has no score
        vals = [by_seed[s] for s in sorted(by_seed) if by_seed[s] is not None]
        scores = ", ".join(
            f"{s}: {'not evaluated' if v is None else format(v, '.1f')}"
            for s, v in sorted(by_seed.items())
        )
        mean = format(sum(vals) / len(vals), ".1f") if vals else "-"
        lines.append(
            f"| {task} | {agent} | {cfg} | {made[(task, agent, cfg)]} | {scores} | {mean} |"
        )
    return "\n".join(lines) + "\n"
