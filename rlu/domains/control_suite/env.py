"""DM Control Suite: the 9 RL Unplugged tasks, as the datasets were recorded.

Original: ``rl_unplugged/dm_control_suite.py`` ``ControlSuite.environment`` =
``suite.load(domain, task)`` with the release's observation keys, float32. Every suite action
spec is already [-1, 1], so rlu's action normalisation is the identity here.

Rendering: camera 0 of each model (cartpole ``fixed``, walker and cheetah ``side``, humanoid
``back``, fish ``tracking_top``), at 1 / control timestep frames per second.

Seeding: ``make_env(task, seed=s)`` is ``suite.load(domain, task, task_kwargs={"random": s})``;
``reset(seed=s)`` reseeds the task's RandomState in place, which is the same thing.
"""

from __future__ import annotations

from typing import Any

from rlu.domains.envkit import DmControlEnv, Render
from rlu.domains.spec import TaskSpec
from rlu.types import RluError


def make(
    task: TaskSpec, seed: int | None = None, render: Render | None = None, **settings: Any
) -> DmControlEnv:
    if settings:
        raise RluError(
            f"{task.id}: unknown env settings {sorted(settings)}; the control suite has none"
        )
    from dm_control import suite

    env = suite.load(task.env["suite_domain"], task.env["suite_task"], task_kwargs={"random": seed})

    def reseed(s: int) -> None:
        env.task.random.seed(s)

    return DmControlEnv(
        env,
        task.observation_spec,  # type: ignore[arg-type]  # dm_control observes a dict
        reseed,
        physics=lambda: env.physics,
        control_timestep=env.control_timestep(),
        name=task.id,
        render=render,
        camera=0,  # each suite model's first camera: the view dm_control's own examples use
    )
