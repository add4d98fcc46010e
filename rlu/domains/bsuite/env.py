"""bsuite: catch, cartpole and mountain_car from the ``bsuite`` package (the ``bsuite`` extra), as
the release's data were recorded.

``make_env("bsuite/catch", seed=0, random_prob=0.1)``: bsuite's environment with its default
settings (bsuite id ``<env>/0``), observations flattened to float32 as the release stores them;
with probability ``random_prob`` (the dataset's noise level, 0.0 to 0.5 in the release; default
0.0) the action taken is replaced by a uniform random one, drawn from the env's own seeded
generator. An episode ends terminated when bsuite's last step has discount 0, truncated
otherwise. ``reset(seed=s)`` makes bsuite's environment again with seed ``s``. No rendering.
"""

from __future__ import annotations

import importlib
from typing import Any

import numpy as np

from rlu.domains.envkit import Render, check_observation, gym, observation_space, spaces
from rlu.domains.spec import TaskSpec
from rlu.types import RluError


class BsuiteEnv(gym.Env):
    """A bsuite environment as a Gymnasium env (see the module docstring)."""

    metadata = {"render_modes": []}
    action_space: spaces.Discrete

    def __init__(self, task: TaskSpec, seed: int | None, random_prob: float) -> None:
        module, cls = task.env["bsuite_class"].split(".")
        self._cls = getattr(importlib.import_module(f"bsuite.environments.{module}"), cls)
        self.task = task
        self.random_prob = float(random_prob)
        self.observation_space = observation_space(task.observation_spec)
        self.action_space = spaces.Discrete(task.action_spec.num_values)  # type: ignore[union-attr]
        self._seed = seed
        self._env: Any = None  # a bsuite (dm_env, untyped) environment once reset

    def _obs(self, ts: Any) -> np.ndarray:
        obs = np.asarray(ts.observation, np.float32).reshape(-1)
        check_observation(obs, self.task.observation_spec, self.task.id)
        return obs

    def reset(
        self, *, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is None and self._env is None:
            seed = self._seed  # make_env's seed seeds the first episode
        super().reset(seed=seed)
        env_seed = seed if seed is not None else int(self.np_random.integers(2**31))
        self._env = self._cls(seed=env_seed)
        return self._obs(self._env.reset()), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._env is None:
            raise RluError(f"{self.task.id}: call reset() before step()")
        a = int(action)
        if not 0 <= a < self.action_space.n:
            raise RluError(f"{self.task.id}: action {a} is not in 0..{self.action_space.n - 1}")
        if self.random_prob > 0 and self.np_random.random() < self.random_prob:
            a = int(self.np_random.integers(self.action_space.n))
        ts = self._env.step(a)
        last = bool(ts.last())
        terminated = last and float(ts.discount) == 0.0
        return self._obs(ts), float(ts.reward), terminated, last and not terminated, {}


def make(
    task: TaskSpec,
    seed: int | None = None,
    render: Render | None = None,
    random_prob: float = 0.0,
    **settings: Any,
) -> BsuiteEnv:
    """The bsuite env of ``task`` (settings: ``random_prob``)."""
    if settings:
        raise RluError(
            f"{task.id}: unknown env settings {sorted(settings)}; bsuite has random_prob"
        )
    if render is not None and render.mode is not None:
        raise RluError(f"{task.id}: bsuite envs do not render; drop render_mode")
    if not 0.0 <= float(random_prob) <= 1.0:
        raise RluError(f"{task.id}: random_prob={random_prob!r} must be within [0, 1]")
    importlib.import_module("bsuite")  # the bsuite extra: an ImportError names it
    return BsuiteEnv(task, seed, random_prob)
