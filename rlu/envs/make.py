"""``make_env``: a task's env from its domain's env module (``Domain.env_module``), with the
settings it was made with as its Gymnasium spec (``env_spec``: what ``gymnasium.make`` of the
task's id would set). ``rlu.envs`` hands it on; the registered ids' entry point
(``rlu.envs.registration.make``) calls it.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Mapping
from types import ModuleType
from typing import TYPE_CHECKING, Any

from rlu.domains import DOMAINS
from rlu.system import install_hint
from rlu.tasks import GYM_ENTRY_POINT, TaskSpec, get_task, resolve_task
from rlu.types import RluError

if TYPE_CHECKING:  # pragma: no cover
    from gymnasium.envs.registration import EnvSpec


def _factory(domain: str) -> ModuleType:
    if DOMAINS[domain].mujoco:
        # MuJoCo needs a GL backend for any rendering; EGL works headless on CPU (Mesa).
        os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        return importlib.import_module(DOMAINS[domain].env_module)
    except ImportError as e:
        extra = DOMAINS[domain].extra
        raise RluError(
            f"environments of domain {domain!r} need the {extra!r} extra ({e.name} is missing); "
            f"install it with: {install_hint(extra)}"
        ) from e


def make_env(
    task_id: str,
    seed: int | None = None,
    challenge: str | None = None,
    *,
    render_mode: str | None = None,
    render_size: tuple[int, int] | None = None,
    render_camera: str | int | None = None,
    **settings: Any,
) -> Any:  # the domain's gymnasium.Env subclass (float rewards, the task's observations)
    """A Gymnasium env for ``task_id`` (``rlu.envs``' docstring lists each domain's ``settings``).

    ``render_mode="rgb_array"`` makes ``env.render()`` return frames (see ``rlu.domains.envkit``);
    ``challenge`` (RWRL) defaults to the one a TFDS name carries, else ``"none"``.
    """
    from rlu.domains.envkit import render_settings

    ref = resolve_task(task_id)
    task = ref.task
    if challenge is None:
        challenge = ref.challenge or "none"
    render = render_settings(task.id, render_mode, render_size, render_camera)
    module = _factory(task.domain)
    if DOMAINS[task.domain].challenges:
        env = module.make(task, seed=seed, challenge=challenge, render=render, **settings)
    elif challenge != "none":
        takes = [d for d, dom in DOMAINS.items() if dom.challenges]
        raise RluError(f"{task.id}: `challenge` applies to {'/'.join(takes)} tasks only; drop it")
    else:
        env = module.make(task, seed=seed, render=render, **settings)

    kwargs: dict[str, Any] = {"seed": seed} if seed is not None else {}
    if challenge != "none":
        kwargs["challenge"] = challenge
    given = {"render_mode": render_mode, "render_size": render_size, "render_camera": render_camera}
    kwargs.update({k: v for k, v in given.items() if v is not None})
    env.spec = env_spec(task, {**kwargs, **settings})
    return env


def env_spec(task: TaskSpec | str, settings: Mapping[str, Any] | None = None) -> EnvSpec:
    """The Gymnasium spec of ``task`` made with ``settings`` (what ``gymnasium.make`` would set)."""
    from gymnasium.envs.registration import EnvSpec

    task = get_task(task) if isinstance(task, str) else task
    kwargs = {"task_id": task.id, **dict(settings or {})}
    return EnvSpec(
        id=task.gym_id,
        entry_point=GYM_ENTRY_POINT,
        kwargs=kwargs,
        max_episode_steps=task.max_episode_steps(kwargs),
        disable_env_checker=False,
    )
