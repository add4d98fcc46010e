"""The recipe around a policy the user supplies (locomotion's path; any task may use it).

``rlu generate TASK --policy package.module:factory``: ``factory(task_id, seed)`` returns a
policy, a callable ``policy(observation) -> action`` for one unbatched observation. Runs and
the recorder are those of ``rlu generate``: ``runs`` runs (the paper: 3 for the CMU humanoid,
5 for the rodent), every episode recorded with its run, seed, checkpoint (the chunk) and episode
index, a third of the successful episodes kept (locomotion: the episode reached its time limit),
then sub-sampled to the paper's episode count.

Determinism and resumption: the policy is built again for every chunk of episodes with a seed
derived from ``(seed, run, chunk)`` and every episode resets the env with its own derived seed,
so a chunk is a function of its seeds alone (the policy must be a function of its seed and the
observations); finished chunks are skipped on resume. The runs play through the one runner, as
the recipe's (a worker process imports the factory again: it must be importable there).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any

from rlu.data import DatasetWriter
from rlu.generate.common import (
    ENV,
    EPISODE,
    POLICY,
    Progress,
    merge_runs,
    open_work,
    paper_count,
    play_runs,
    report_episode,
    run_seed,
    success_rule,
)
from rlu.generate.config import GenerateConfig
from rlu.generate.recorder import EpisodeRecorder, episode_id, record_policy, schema_for
from rlu.tasks import TaskSpec, get_task
from rlu.types import RluError


@dataclasses.dataclass(frozen=True)
class PolicyScale:
    runs: int
    """Runs; the paper: 3 (CMU humanoid), 5 (rodent)."""
    episodes: int
    """Episodes per run."""
    chunk_episodes: int
    """Episodes per saved part (and per policy build)."""


def policy_scale(task: TaskSpec, scale: str) -> PolicyScale:
    """The behaviour-policy runs, episodes per run and episodes per saved part of ``task`` at
    ``scale`` (``tiny``, ``laptop``, ``paper``)."""
    runs = 5 if task.env.get("walker") == "rodent" else 3
    target = int(task.episodes.get("", 100))
    return {
        "tiny": PolicyScale(1, 2, 1),
        "laptop": PolicyScale(runs, 10, 5),
        # enough episodes that the target remains after two thirds of the successes go
        "paper": PolicyScale(runs, -(-3 * target // runs), 20),
    }[scale]


def load_factory(spec: str) -> Any:
    """``'package.module:function'`` -> the function; the working directory is importable, as
    for ``python -m``."""
    import importlib
    import os
    import sys

    module, _, attr = spec.partition(":")
    if not module or not attr:
        raise RluError(f"--policy {spec!r}; write it as 'package.module:factory'")
    if os.getcwd() not in sys.path:
        sys.path.append(os.getcwd())
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as e:
        raise RluError(f"--policy {spec!r} cannot be imported: {e}") from None


def play_policy_run(config: GenerateConfig, scale: PolicyScale, run: int, work: Path) -> None:
    """One run's job: record its unfinished chunks into ``work/run_RRR``."""
    from rlu.envs import make_env

    task = get_task(config.task)
    seed, schema = config.seed, schema_for(task)
    episodes, chunk_episodes = scale.episodes, scale.chunk_episodes
    assert config.policy is not None  # generate() comes here only with a policy
    factory = load_factory(config.policy)
    env = None
    for c in range(-(-episodes // chunk_episodes)):
        part = work / f"run_{run:03d}" / f"part_{c:05d}"
        if (part / "manifest.json").exists():
            continue
        if env is None:
            env = make_env(task.id, seed=run_seed(seed, run, ENV))
        pi = factory(task.id, run_seed(seed, run, POLICY, c))
        rec = EpisodeRecorder(task)
        with DatasetWriter(part, schema, overwrite=True) as w:
            first = c * chunk_episodes
            for e in range(first, min(episodes, first + chunk_episodes)):
                meta = {
                    "run": run,
                    "seed": seed,
                    "checkpoint": c,
                    "episode_index": e,
                    "episode_id": episode_id(run, e),
                }
                seg = record_policy(env, pi, rec, run_seed(seed, run, EPISODE, e), meta)
                w.append(seg)
                report_episode(run, e + 1, seg)
    if env is not None:
        env.close()


def generate_with_policy(config: GenerateConfig, task: TaskSpec, out: Path, work: Path) -> Path:
    """Record ``config.policy`` (see the module docstring) into the claimed ``work`` folder;
    returns the dataset's path."""
    sc = policy_scale(task, config.scale)
    runs = sc.runs if config.runs is None else config.runs
    assert config.policy is not None  # generate() comes here only with a policy
    load_factory(config.policy)  # a typo fails here, before any run
    target = paper_count(task)
    settings = json.loads(
        json.dumps(
            {
                "task": task.id,
                "scale": config.scale,
                "runs": runs,
                "seed": config.seed,
                "policy": config.policy,
                "episodes_per_run": sc.episodes,
                "chunk_episodes": sc.chunk_episodes,
                "env_settings": {},
                "target_episodes": target,
                "success_rule": success_rule(task),
            }
        )
    )
    cmd = config.command(runs)
    open_work(work, settings, f"{cmd} --out {out}")
    bar = Progress(runs * sc.episodes, task.id, config.progress)
    jobs = [(config, sc, r, work) for r in range(runs)]
    play_runs(config, play_policy_run, jobs, bar)
    bar.close()
    path = merge_runs(task, work, out, settings, cmd + " --out DIR")
    if not config.keep_work:
        shutil.rmtree(work)
    return path


__all__ = ["generate_with_policy", "policy_scale"]
