"""The data-generation recipes: online behaviour agents, the episode recorder, sub-sampling.

    from rlu.generate import generate
    generate("control_suite/cartpole_swingup", "data/cartpole", scale="laptop", seed=0)

``generate`` picks one of three peer recipes: ``recipe`` (D4PG / DQN training runs: the control
suite and Atari), ``rwrl`` (fixed behaviour snapshots, D4PG or at the paper scale DMPO, rolled
out with and without challenges) and ``policy`` (a policy the user supplies: locomotion). They
share ``common`` (success rule, selection, merge, progress) and ``scales``; ``online`` is the
actor-learner loop and ``recorder`` turns env steps into store segments. Heavy dependencies
(torch, the simulators) load only when a run starts.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from rlu.devices import check_gpus_per_run
from rlu.generate.common import select_episodes, success_rule
from rlu.generate.scales import SCALES, check_scale
from rlu.tasks import get_task
from rlu.types import RluError


def generate(
    task_id: str,
    out: str | Path,
    scale: str = "laptop",
    runs: int | None = None,
    seed: int = 0,
    backend: str = "local",
    progress: bool = True,
    on_chunk: Callable[[int, int], None] | None = None,
    keep_work: bool = False,
    policy: str | None = None,
    workers: int | None = None,
    device: str = "cpu",
    gpus_per_run: float = 0.0,
) -> Path:
    """Record a dataset for ``task_id`` into ``out``; returns its path (for RWRL, the folder of
    its ``{challenge}_{size}`` datasets). ``runs``: independent runs (default: the scale's);
    ``policy`` ('module:factory', see ``rlu.generate.policy``) records a user policy instead of
    training the behaviour agent (required for locomotion); ``on_chunk(run, chunk)`` is called
    after every saved chunk (tests interrupt there); ``workers``: processes for the runs (the
    D4PG / DQN recipe; default one per run). The behaviour agents learn on ``device``; on Ray
    each run asks for ``gpus_per_run`` GPUs (a fraction shares one)."""
    task = get_task(task_id)
    check_scale(scale)
    check_gpus_per_run(gpus_per_run)
    if gpus_per_run and backend != "ray":
        raise RluError("--gpus-per-run asks Ray for GPUs; use it with --backend ray")
    out = Path(out)
    if policy is not None or task.domain == "locomotion":
        from rlu.generate.policy import generate_with_policy

        if policy is None:
            raise RluError(
                f"{task.id}: locomotion data comes from a policy you supply: pass --policy "
                "package.module:factory, factory(task_id, seed) -> policy(observation) -> action"
            )
        if backend != "local":
            raise RluError("--policy runs with --backend local only")
        return generate_with_policy(task, out, scale, runs, seed, policy, progress, keep_work)
    if task.domain == "rwrl":
        from rlu.generate.rwrl import generate_rwrl

        if backend != "local":
            raise RluError("rwrl generation runs with --backend local only")
        return generate_rwrl(task, out, scale, runs, seed, progress, keep_work, device)
    from rlu.generate.recipe import generate_runs

    return generate_runs(task, out, scale, runs, seed, backend, progress, on_chunk, keep_work,
                         workers, device, gpus_per_run)  # fmt: skip


__all__ = ["SCALES", "generate", "select_episodes", "success_rule"]
