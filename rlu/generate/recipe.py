"""The paper's recipe around online training runs (D4PG for the control suite, DQN for Atari).

``generate_runs(config, task, out, work)`` (``rlu.generate.generate`` calls it):

1. plays ``runs`` independent online training runs of the behaviour agent
   (``rlu.generate.online``) and records every episode with its run, seed, checkpoint and
   episode index;
2. keeps a third of the successful episodes and sub-samples to the task's episode count
   (``rlu.generate.common``: the success rule and the selection);
3. writes one dataset whose manifest holds the command, the seed, the resolved settings, the
   behaviour agent's config, the success rule and the selection counts (no clock time, so the same
   seed gives the same bytes), with the behaviour policy of every (run, checkpoint) its episodes
   name under ``policies/`` (``rlu.generate.policies``: kept at the first episode of each
   checkpoint id, weights only, loaded without pickle).

The runs play through the one runner (``rlu.workers.run_jobs``: in this process, in local worker
processes or on Ray; the bytes do not depend on where). Resumption: the work goes to
``.<out>.generate/`` next to ``out``: one store part per chunk of episodes per run, written
atomically, and a per-run ``state.pt`` (agent, replay, random generator) saved after each
part. Re-running the same command resumes every unfinished run from its last saved chunk and
gives the bytes of an uninterrupted run; the work folder is removed once the dataset is written.
Settings that differ from the interrupted run's are an error, and so is a damaged file there.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rlu.data import DatasetWriter
from rlu.generate.common import (
    Progress,
    merge_runs,
    open_work,
    paper_count,
    play_runs,
    report_episode,
    success_rule,
)
from rlu.generate.config import GenerateConfig
from rlu.generate.online import OnlineConfig, RunHooks, run_online
from rlu.generate.policies import save_snapshot
from rlu.generate.recorder import schema_for
from rlu.generate.scales import get_scale
from rlu.segments import Segment
from rlu.tasks import TaskSpec, get_task
from rlu.types import RluError


def _part_path(work: Path, run: int, chunk: int) -> Path:
    return work / f"run_{run:03d}" / f"part_{chunk:05d}"


def play_run(
    config: GenerateConfig,
    online: OnlineConfig,
    run: int,
    work: Path,
    on_chunk: Callable[[int, int], None] | None = None,
) -> None:
    """One run's job: play it (or resume it) into ``work/run_RRR``, its parts and policies."""
    task = get_task(config.task)
    schema = schema_for(task)
    run_dir = work / f"run_{run:03d}"

    def write_chunk(chunk: int, segs: list[Segment]) -> None:
        with DatasetWriter(_part_path(work, run, chunk), schema, overwrite=True) as w:
            for s in segs:
                w.append(s)

    def keep_policy(checkpoint: int, env_steps: int, episode: int, agent: Any) -> None:
        save_snapshot(
            run_dir / "policies",
            agent,
            task,
            online,
            config.seed,
            run,
            checkpoint,
            env_steps,
            episode,
        )

    hooks = RunHooks(write_chunk, report_episode, on_chunk, on_checkpoint=keep_policy)
    run_online(config, online, run, run_dir, hooks)


def generate_runs(
    config: GenerateConfig,
    task: TaskSpec,
    out: Path,
    work: Path,
    on_chunk: Callable[[int, int], None] | None = None,
) -> Path:
    """Run the recipe (see the module docstring) into the claimed ``work`` folder; returns the
    dataset's path. ``on_chunk(run, chunk)`` is called after every saved chunk, in this
    process (tests interrupt there)."""
    sc = get_scale(task, config.scale)
    runs = sc.runs if config.runs is None else config.runs
    backend = config.backend
    if on_chunk is not None and (backend.kind != "local" or (backend.workers > 1 and runs > 1)):
        raise RluError("on_chunk is called in the generating process: use one local worker")
    target = sc.target_episodes if sc.target_episodes is not None else paper_count(task)
    from rlu.agents import make_config

    agent_cfg = make_config(
        sc.online.agent, task.discrete, sc.online.preset, **sc.online.agent_overrides
    )
    settings = {
        "task": task.id,
        "scale": config.scale,
        "runs": runs,
        "seed": config.seed,
        "online": sc.online.to_json(),
        "agent_config": dataclasses.asdict(agent_cfg),
        "target_episodes": target,
        "success_rule": success_rule(task),
    }
    settings = json.loads(json.dumps(settings))  # tuples -> lists, as read back
    command = config.command(runs)
    open_work(work, settings, f"{command} --out {out}")

    bar = Progress(
        runs * sc.online.episodes if sc.online.env_steps is None else 0, task.id, config.progress
    )
    jobs = [(config, sc.online, r, work, on_chunk) for r in range(runs)]
    play_runs(config, play_run, jobs, bar)
    bar.close()
    dtype = sc.online.policy_dtype
    path = merge_runs(task, work, out, settings, command + " --out DIR", policies=dtype)
    if not config.keep_work:
        shutil.rmtree(work)
    return path
