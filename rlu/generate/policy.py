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
observations); finished chunks are skipped on resume.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any

from rlu.data import DatasetWriter
from rlu.generate.common import Progress, merge_runs, open_work, paper_count, success_rule
from rlu.generate.online import derive_seed
from rlu.generate.recorder import EpisodeRecorder, episode_id, schema_for
from rlu.tasks import TaskSpec
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


def generate_with_policy(task: TaskSpec, out: Path, scale: str, runs: int | None, seed: int,
                         policy: str, progress: bool = True, keep_work: bool = False,
                         env_settings: dict | None = None) -> Path:  # fmt: skip
    from rlu.envs import make_env

    sc = policy_scale(task, scale)
    runs = sc.runs if runs is None else int(runs)
    factory = load_factory(policy)
    out = Path(out)
    if (out / "manifest.json").exists():
        raise RluError(f"{out} already holds a dataset; choose another --out or remove it")
    target = paper_count(task)
    settings = json.loads(json.dumps({
        "task": task.id, "scale": scale, "runs": runs, "seed": seed, "policy": policy,
        "episodes_per_run": sc.episodes, "chunk_episodes": sc.chunk_episodes,
        "env_settings": env_settings or {}, "target_episodes": target,
        "success_rule": success_rule(task),
    }))  # fmt: skip
    work = out.parent / f".{out.name}.generate"
    cmd = f"rlu generate {task.id} --scale {scale} --seeds {runs} --seed {seed} --policy {policy}"
    open_work(work, settings, f"{cmd} --out {out}")
    schema = schema_for(task)
    bar = Progress(runs * sc.episodes, task.id, progress)
    for r in range(runs):
        env = None
        for c in range(-(-sc.episodes // sc.chunk_episodes)):
            part = work / f"run_{r:03d}" / f"part_{c:05d}"
            if (part / "manifest.json").exists():
                continue
            if env is None:
                env = make_env(task.id, seed=derive_seed(seed, r), **(env_settings or {}))
            pi = factory(task.id, derive_seed(seed, r, 6, c))
            rec = EpisodeRecorder(task, env_settings and env_settings.get("max_episode_steps"))
            with DatasetWriter(part, schema, overwrite=True) as w:
                first = c * sc.chunk_episodes
                for e in range(first, min(sc.episodes, first + sc.chunk_episodes)):
                    meta = {"run": r, "seed": seed, "checkpoint": c, "episode_index": e,
                            "episode_id": episode_id(r, e)}  # fmt: skip
                    obs, _ = env.reset(seed=derive_seed(seed, r, 2, e))
                    rec.begin(obs)
                    while True:
                        a = pi(obs)
                        obs, rew, term, trunc, info = env.step(a)
                        seg = rec.step(a, rew, obs, term, trunc, info, meta)
                        if seg is not None:
                            break
                    w.append(seg)
                    bar.update(r, e + 1, seg)
        if env is not None:
            env.close()
    bar.close()
    path = merge_runs(task, work, runs, settings, target, seed, out, cmd + " --out DIR")
    if not keep_work:
        shutil.rmtree(work)
    return path


__all__ = ["generate_with_policy", "policy_scale"]
