"""The data-generation recipes: online behaviour agents, the episode recorder, sub-sampling.

    from rlu.generate import GenerateConfig, generate
    generate(GenerateConfig("control_suite/cartpole_swingup", scale="laptop", seed=0), "data/cp")

One frozen :class:`GenerateConfig` (``config``) says what to record and how to run; ``generate``
passes it whole to one of three peer recipes (``Domain.generation`` names one): ``recipe``
(``runs``: D4PG / DQN training runs, the control suite and Atari), ``rwrl`` (``snapshots``: fixed
behaviour snapshots, D4PG or at the paper scale DMPO, rolled out with and without challenges)
and ``policy`` (a policy the user supplies: locomotion). They
share ``common`` (seeds, success rule, selection, work folder, the runner, merge, progress) and
``scales``; ``online`` is the actor-learner loop and its replay (the store's n-step and frame
stack maths), ``recorder`` turns env steps into store segments. Heavy dependencies (torch, the
simulators) load only when a run starts.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from rlu.domains import DOMAINS
from rlu.generate.common import claim_work, select_episodes, success_rule, work_folder
from rlu.generate.config import SCALES, GenerateConfig
from rlu.tasks import TaskSpec, get_task
from rlu.types import RluError


def _recipe(config: GenerateConfig, task: TaskSpec) -> str:
    recipe = DOMAINS[task.domain].generation
    if recipe is None:
        raise RluError(f"{task.id}: rlu generate makes no data for domain {task.domain!r}")
    if config.policy is not None or recipe == "policy":
        if config.policy is None:
            raise RluError(
                f"{task.id}: {task.domain} data comes from a policy you supply: pass --policy "
                "package.module:factory, factory(task_id, seed) -> policy(observation) -> action"
            )
        return "policy"
    return recipe


def run_count(config: GenerateConfig) -> int:
    """The runs ``config`` plays: its ``runs``, else its scale's."""
    if config.runs is not None:
        return config.runs
    task = get_task(config.task)
    if _recipe(config, task) == "policy":
        from rlu.generate.policy import policy_scale

        return policy_scale(task, config.scale).runs
    from rlu.generate.scales import get_scale

    return get_scale(task, config.scale).runs


def _check_out(out: Path, kind: str) -> None:
    """Refuse, before anything is touched, an ``out`` that is not a new dataset folder (RWRL:
    a folder its own interrupted generation started)."""
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise RluError(f"--out {out} exists and is not a folder; choose another --out")
    if kind == "snapshots":
        from rlu.generate.rwrl import SUMMARY

        if (out / SUMMARY).exists():
            raise RluError(f"{out} already holds RWRL datasets; choose another --out or remove it")
        if (
            out.is_dir()
            and any(out.iterdir())
            and not (work_folder(out) / "settings.json").exists()
        ):
            raise RluError(
                f"--out {out} exists and is not an interrupted rlu generate of RWRL datasets; "
                "choose a new --out or empty that folder yourself"
            )
        return
    if (out / "manifest.json").exists():
        raise RluError(f"{out} already holds a dataset; choose another --out or remove it")
    if out.exists():
        raise RluError(
            f"--out {out} already exists; rlu generate writes a new dataset folder: choose "
            "another --out or remove it"
        )


def generate(
    config: GenerateConfig,
    out: str | Path,
    on_chunk: Callable[[int, int], None] | None = None,
) -> Path:
    """Record the dataset ``config`` describes into ``out``; returns its path (for RWRL, the
    folder of its ``{challenge}_{size}`` datasets). Re-running an interrupted generation with
    the same config resumes it to the same bytes. One generation per ``out`` at a time: a
    second one fails at once with "in use by PID N". ``on_chunk(run, chunk)`` is called after
    every saved chunk of the D4PG / DQN recipe, in this process (tests interrupt there). A Ray
    backend at a HOST:PORT that does not answer is refused in seconds, before anything is
    written (``rlu.workers.Backend.reach``)."""
    if not isinstance(config, GenerateConfig):
        raise RluError(
            f"generate takes a rlu.generate.GenerateConfig, got {type(config).__name__}; build "
            "one with GenerateConfig(task_id, scale=..., runs=..., seed=...)"
        )
    task = get_task(config.task)
    kind = _recipe(config, task)
    if on_chunk is not None and kind != "runs":
        raise RluError("on_chunk is called by the D4PG / DQN recipe only")
    out = Path(out)
    _check_out(out, kind)
    config.backend.reach()  # before the work folder's lock: a dead cluster leaves nothing
    with claim_work(out) as work:
        _check_out(out, kind)  # one that finished between the check and the claim
        if kind == "policy":
            from rlu.generate.policy import generate_with_policy

            return generate_with_policy(config, task, out, work)
        if kind == "snapshots":
            from rlu.generate.rwrl import generate_rwrl

            return generate_rwrl(config, task, out, work)
        from rlu.generate.recipe import generate_runs

        return generate_runs(config, task, out, work, on_chunk)


__all__ = ["SCALES", "GenerateConfig", "generate", "run_count", "select_episodes", "success_rule"]
