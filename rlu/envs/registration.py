"""Every task as a Gymnasium id in the ``rlu`` namespace.

    import gymnasium as gym
    import rlu.envs                                    # registers the ids (imports gymnasium)
    env = gym.make("rlu/control_suite-cartpole_swingup-v0")
    env = gym.make("rlu/rwrl-walker_walk-v0", challenge="easy")
    env = gym.make("rlu/atari-Pong-v0", clip_rewards=False)
    env = gym.make("rlu.envs:rlu/atari-Pong-v0")        # Gymnasium's import-then-make form

The id of task ``DOMAIN/NAME`` is ``rlu/DOMAIN-NAME-v0`` (``gym_id``): one namespace, the domain
kept because RWRL and the control suite share task names. Keyword arguments of ``gymnasium.make``
are the task's settings, as for ``rlu.make_env`` (see ``rlu.envs``); the spec's entry point is
``rlu.envs.registration:make`` with ``task_id`` in its kwargs, a string, so that a spec written
to JSON (Minari stores one with each dataset) makes the same env again.

Gymnasium 1.x has no plugin entry points (they went in 1.0), so the ids exist once ``rlu.envs``
is imported; ``import rlu`` alone stays numpy-only.

Time limits are the env's own, as the data were recorded (dm_control's time limit with its
discount, Atari's ``max_episode_steps`` setting in agent steps); the spec's ``max_episode_steps``
says what that limit is in agent steps (``TaskSpec.episode_length``, or the Atari setting), so
the ``TimeLimit`` that ``gymnasium.make`` wraps around the env ends an episode at the very step
the env itself does, and code that reads ``env.spec.max_episode_steps`` (Gymnasium's wrappers,
Minari, replay buffers) sees the real length. ``gymnasium.make`` takes ``max_episode_steps`` for
itself: its ``TimeLimit`` can shorten episodes, not lengthen them, since the env keeps its own
limit; for a longer Atari limit use ``rlu.make_env(..., max_episode_steps=N)`` (and
``gymnasium.make(that_env.spec)`` makes it again).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from rlu.tasks import GYM_ENTRY_POINT, GYM_NAMESPACE, GYM_VERSION, get_task, list_tasks
from rlu.types import RluError


def gym_id(task_id: str) -> str:
    """``control_suite/cartpole_swingup`` -> ``rlu/control_suite-cartpole_swingup-v0``."""
    return get_task(task_id).gym_id


def task_id_of(env_id: str) -> str:
    """The task id of an rlu Gymnasium id (``rlu/atari-Pong-v0`` -> ``atari/Pong``)."""
    prefix, suffix = f"{GYM_NAMESPACE}/", f"-v{GYM_VERSION}"
    body = env_id.removeprefix(prefix).removesuffix(suffix)
    domain, sep, name = body.partition("-")
    if not env_id.startswith(prefix) or not sep:
        raise RluError(f"{env_id!r} is not an rlu Gymnasium id; they read rlu/DOMAIN-NAME-v0")
    return get_task(f"{domain}/{name}").id


def make(task_id: str, **settings: Any) -> gym.Env:
    """The entry point of every registered id: ``rlu.make_env(task_id, **settings)``."""
    from rlu.envs.make import make_env

    return make_env(task_id, **settings)


def register_envs() -> None:
    """Register every task's id (idempotent: ids already registered are left alone)."""
    for task in list_tasks():
        if task.gym_id not in gym.registry:
            gym.register(
                id=task.gym_id,
                entry_point=GYM_ENTRY_POINT,
                kwargs={"task_id": task.id},
                max_episode_steps=task.max_episode_steps(),
            )
