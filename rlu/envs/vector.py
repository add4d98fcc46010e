"""Vectorised evaluation envs: N copies of a task behind Gymnasium's VectorEnv interface.

    venv = make_vector_env("control_suite/walker_walk", num_envs=2, seed=0)
    obs, info = venv.reset()             # dict of (N, ...) arrays, or (N, 84, 84, 4) for Atari
    obs, reward, terminated, truncated, info = venv.step(actions)

Backends:
- ``"async"`` (MuJoCo default): ``gymnasium.vector.AsyncVectorEnv``, one worker process per env
  running ``rlu.make_env``; env i gets seed ``seed + i``, so every sub-env is exactly the single
  env of that seed. MuJoCo workers start through ``forkserver`` so that no GL context is ever
  inherited across a fork.
- ``"ale"`` (Atari default): ale-py's C++ ``AtariVectorEnv`` with rlu's settings (sticky 0.25,
  no no-ops, no fire reset, frame skip 4 with max-pool, 84x84 grey, 4 frames zero-padded at an
  episode start, newest last). Its frames were checked to be bit-identical to ``AtariEnv``'s
  under the same actions (tests/envs/test_vector.py); its seeding differs from the single env's,
  so a sub-env is not the single env of some seed. Observations are transposed to (N, 84, 84, 4)
  and rewards clipped as the single env does (``info["raw_reward"]`` unclipped). It runs its
  own thread pool and measured faster than processes (bench/envs.py).
- ``"sync"``: ``gymnasium.vector.SyncVectorEnv`` in this process (debugging).

All backends use Gymnasium's default autoreset mode (next step): after a sub-env's episode ends,
its next ``step`` ignores the action and returns the first observation of a new episode.
"""

from __future__ import annotations

import functools
import os
from typing import Any

import numpy as np

from rlu.envs.core import gym, spaces
from rlu.tasks import ATARI_MAX_AGENT_STEPS, get_task
from rlu.types import RluError


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _make_one(task_id: str, seed: int | None, challenge: str, settings: dict[str, Any]):
    from rlu.envs import make_env

    return make_env(task_id, seed=seed, challenge=challenge, **settings)


def make_vector_env(
    task_id: str,
    num_envs: int | None = None,
    seed: int | None = None,
    challenge: str = "none",
    backend: str = "auto",
    **settings: Any,
) -> gym.vector.VectorEnv:
    """``num_envs`` (default: the available cores) copies of ``task_id``; see the module doc."""
    task = get_task(task_id)
    n = int(num_envs or available_cores())
    if n < 1:
        raise RluError(f"num_envs must be >= 1, got {num_envs}")
    if backend == "auto":
        backend = "ale" if task.domain == "atari" else "async"
    if backend == "ale":
        if task.domain != "atari":
            raise RluError(f"{task.id}: backend 'ale' is for Atari tasks; use 'async'")
        return AleVectorEnv(task.env["game"], n, seed, **settings)
    fns = [
        functools.partial(
            _make_one, task.id, None if seed is None else seed + i, challenge, settings
        )
        for i in range(n)
    ]
    if backend == "sync":
        return gym.vector.SyncVectorEnv(fns)
    if backend == "async":
        context = "forkserver" if task.domain != "atari" else None
        return gym.vector.AsyncVectorEnv(fns, context=context)
    raise RluError(f"unknown vector backend {backend!r}; use auto, async, ale or sync")


class AleVectorEnv(gym.vector.VectorEnv):
    """ale-py's AtariVectorEnv with rlu's observation layout and reward convention."""

    def __init__(
        self,
        game: str,
        num_envs: int,
        seed: int | None = None,
        *,
        max_episode_steps: int = ATARI_MAX_AGENT_STEPS,
        clip_rewards: bool = True,
        sticky_action_prob: float = 0.25,
        frame_skip: int = 4,
        num_threads: int | None = None,
    ) -> None:
        from ale_py.vector_env import AtariVectorEnv

        from rlu.envs.atari import SCREEN_SIZE, rom_id

        self._env = AtariVectorEnv(
            rom_id(game),
            num_envs,
            num_threads=num_threads or min(num_envs, available_cores()),
            repeat_action_probability=sticky_action_prob,
            noop_max=0,
            use_fire_reset=False,
            episodic_life=False,
            reward_clipping=False,
            frameskip=frame_skip,
            maxpool=True,
            stack_num=4,
            grayscale=True,
            img_height=SCREEN_SIZE,
            img_width=SCREEN_SIZE,
            # ALE counts frames; the single env counts agent steps of `frame_skip` frames.
            max_num_frames_per_episode=max_episode_steps * frame_skip,
        )
        self.num_envs = num_envs
        self._seed = seed
        self.clip_rewards = clip_rewards
        n_actions = self._env.single_action_space.n
        self.single_observation_space = spaces.Box(0, 255, (SCREEN_SIZE, SCREEN_SIZE, 4), np.uint8)
        self.single_action_space = spaces.Discrete(n_actions)
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, num_envs
        )
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self.metadata = {"autoreset_mode": gym.vector.AutoresetMode.NEXT_STEP}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is None and self._seed is not None:
            seed, self._seed = self._seed, None  # the constructor's seed seeds the first reset
        obs, info = self._env.reset(seed=seed, options=options)
        return np.ascontiguousarray(obs.transpose(0, 2, 3, 1)), info

    def step(self, actions: Any):
        obs, reward, terminated, truncated, info = self._env.step(np.asarray(actions))
        raw = np.asarray(reward, np.float64)
        info = dict(info)
        info["raw_reward"] = raw
        out = np.clip(raw, -1.0, 1.0) if self.clip_rewards else raw
        obs = np.ascontiguousarray(obs.transpose(0, 2, 3, 1))
        return obs, out, terminated, truncated, info

    def close(self, **kwargs: Any) -> None:
        self._env.close()
