"""The paper's recipe around online training runs (D4PG for the control suite, DQN for Atari).

``generate_runs(task, out, scale, runs, seed)``:

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

Resumption: the work goes to ``.<out>.generate/`` next to ``out``: one store part per chunk of
episodes per run, written atomically, and a per-run ``state.pt`` (agent, replay, random
generator) saved after each part. Re-running the same command resumes every unfinished run
from its last saved chunk and gives the bytes of an uninterrupted run; the work folder is
removed once the dataset is written. Settings that differ from the interrupted run's are an
error.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rlu.data import DatasetWriter
from rlu.data.episode import Segment
from rlu.devices import check_ray_gpus, ray_options
from rlu.generate.common import (
    Progress,
    command_line,
    merge_runs,
    open_work,
    paper_count,
    success_rule,
)
from rlu.generate.online import OnlineConfig, run_online
from rlu.generate.policies import save_snapshot
from rlu.generate.recorder import schema_for
from rlu.generate.scales import get_scale
from rlu.tasks import TaskSpec, get_task
from rlu.types import RluError
from rlu.workers import die_with_parent


def _part_path(work: Path, run: int, chunk: int) -> Path:
    return work / f"run_{run:03d}" / f"part_{chunk:05d}"


def _run_one(task_id: str, online: OnlineConfig, seed: int, run: int, work: str,
             on_chunk=None, on_episode=None, device: str = "cpu") -> None:  # fmt: skip
    task = get_task(task_id)
    schema = schema_for(task)

    def write_chunk(chunk: int, segs: list[Segment]) -> None:
        with DatasetWriter(_part_path(Path(work), run, chunk), schema, overwrite=True) as w:
            for s in segs:
                w.append(s)

    run_dir = Path(work) / f"run_{run:03d}"

    def keep_policy(checkpoint: int, env_steps: int, episode: int, agent: Any) -> None:
        save_snapshot(run_dir / "policies", agent, task, online, seed, run, checkpoint,
                      env_steps, episode)  # fmt: skip

    run_online(task, online, seed, run, run_dir, write_chunk, on_episode, on_chunk,
               device=device, on_checkpoint=keep_policy)  # fmt: skip


_QUEUE: Any = None  # a worker process's channel to the parent's progress bar


def _init_worker(queue: Any, parent: int) -> None:
    global _QUEUE
    die_with_parent(parent)  # a killed generate leaves no run playing on, holding its lock
    _QUEUE = queue


def _report(run: int, episode: int, seg: Segment) -> None:
    _QUEUE.put((run, episode, float(seg.metadata["episode_return"])))


def _run_in_worker(task_id: str, online: OnlineConfig, seed: int, run: int, work: str,
                   device: str) -> None:  # fmt: skip
    _run_one(task_id, online, seed, run, work, on_episode=_report, device=device)


def _run_processes(task_id: str, online: OnlineConfig, seed: int, runs: int, work: str,
                   workers: int, bar: Progress, device: str = "cpu") -> None:  # fmt: skip
    """The runs in ``workers`` processes. Each run is a function of (seed, run) alone and torch
    runs one thread in each, so the bytes equal one process's. Spawned, not forked: a fork of a
    process whose OpenMP pool has run can hang."""
    import multiprocessing as mp
    import queue as queue_lib
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = mp.get_context("spawn")
    channel = ctx.Queue()
    with ProcessPoolExecutor(workers, ctx, _init_worker, (channel, os.getpid())) as pool:
        pending = {pool.submit(_run_in_worker, task_id, online, seed, r, work, device)
                   for r in range(runs)}  # fmt: skip
        try:
            while pending:
                done, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                for f in done:
                    f.result()  # a run's error, raised here
                while True:
                    try:
                        bar.report(*channel.get_nowait())
                    except queue_lib.Empty:
                        break
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            raise


def generate_runs(
    task: TaskSpec,
    out: Path,
    scale: str,
    runs: int | None = None,
    seed: int = 0,
    backend: str = "local",
    progress: bool = True,
    on_chunk: Callable[[int, int], None] | None = None,
    keep_work: bool = False,
    workers: int | None = None,
    device: str = "cpu",
    gpus_per_run: float = 0.0,
) -> Path:
    """Run the recipe (see the module docstring); returns the dataset's path. ``workers``:
    processes the local backend runs the runs in (default: one per run; 3 runs on 2 cores take
    1.5 runs' time, where 2 workers take 2); the bytes do not depend on it. The behaviour agents
    learn on ``device``; on Ray each run asks for ``gpus_per_run`` GPUs (a fraction shares one)."""
    sc = get_scale(task, scale)
    runs = sc.runs if runs is None else int(runs)
    if runs < 1:
        raise RluError(f"--seeds {runs}: give at least 1 run")
    workers = runs if workers is None else int(workers)
    if workers < 1:
        raise RluError(f"--workers {workers}: give at least 1 process")
    if on_chunk is not None and workers > 1 and runs > 1:
        raise RluError("on_chunk is called in the generating process: pass workers=1")
    if backend not in ("local", "ray"):
        raise RluError(f"unknown --backend {backend!r}; use 'local' or 'ray'")
    if (out / "manifest.json").exists():
        raise RluError(f"{out} already holds a dataset; choose another --out or remove it")
    target = sc.target_episodes if sc.target_episodes is not None else paper_count(task)
    from rlu.agents import make_config

    agent_cfg = make_config(sc.online.agent, task.discrete, sc.online.preset,
                            **sc.online.agent_overrides)  # fmt: skip
    settings = {
        "task": task.id,
        "scale": scale,
        "runs": runs,
        "seed": int(seed),
        "online": sc.online.to_json(),
        "agent_config": dataclasses.asdict(agent_cfg),
        "target_episodes": target,
        "success_rule": success_rule(task),
    }
    settings = json.loads(json.dumps(settings))  # tuples -> lists, as read back
    work = out.parent / f".{out.name}.generate"
    command = command_line(task.id, scale, runs, seed)
    open_work(work, settings, f"{command} --out {out}")

    bar = Progress(runs * sc.online.episodes if sc.online.env_steps is None else 0,
                   task.id, progress)  # fmt: skip
    if backend == "local" and (workers == 1 or runs == 1):
        for r in range(runs):
            _run_one(task.id, sc.online, seed, r, str(work), on_chunk, bar.update, device)
    elif backend == "local":
        _run_processes(task.id, sc.online, seed, runs, str(work), min(workers, runs), bar,
                       device)  # fmt: skip
    else:
        _run_ray(task.id, sc.online, seed, runs, str(work), device, gpus_per_run)
    bar.close()
    path = merge_runs(task, work, runs, settings, target, seed, out, command + " --out DIR",
                      policies=sc.online.policy_dtype)  # fmt: skip
    if not keep_work:
        shutil.rmtree(work)
    return path


def _run_ray(task_id: str, online: OnlineConfig, seed: int, runs: int, work: str,
             device: str = "cpu", gpus_per_run: float = 0.0) -> None:  # fmt: skip
    try:
        import ray
    except ImportError as e:
        raise RluError(
            "--backend ray needs the 'distributed' extra: bash scripts/install.sh distributed"
        ) from e
    started = not ray.is_initialized()
    if started:
        ray.init(ignore_reinit_error=True, log_to_driver=False, include_dashboard=False)
    try:
        check_ray_gpus(ray, gpus_per_run, device)
        remote = ray.remote(**ray_options(gpus_per_run))(_run_one)
        # Runs share nothing but the work folder, which must be on a filesystem every node sees;
        # each run is a function of (seed, run) alone, so the bytes equal the local backend's.
        ray.get([remote.remote(task_id, online, seed, r, work, device=device)
                 for r in range(runs)])  # fmt: skip
    finally:
        if started:
            ray.shutdown()


BUNDLED_TASK = "control_suite/cartpole_swingup"


def bundled_dataset(task_id: str = BUNDLED_TASK) -> Path:
    """The dataset shipped in the package (made by ``rlu generate``; its manifest holds the
    command and seed)."""
    from importlib import resources

    path = Path(str(resources.files("rlu"))) / "resources" / "datasets" / task_id
    if not (path / "manifest.json").exists():
        raise RluError(
            f"{path}: no bundled dataset for {task_id!r}; the package ships {BUNDLED_TASK} only "
            "(reinstall rlu if it is missing)"
        )
    return path
