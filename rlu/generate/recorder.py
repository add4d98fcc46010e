"""Records episodes from an env loop as store segments (RLDS step semantics).

One ``EpisodeRecorder`` per env. ``begin(obs)`` after ``env.reset()``, ``step(...)`` after every
``env.step()``; the step that ends the episode returns its :class:`rlu.data.Segment`:

- ``terminated`` (Gymnasium) -> a terminal final step (discount 0 on the last transition);
  ``truncated`` (a time limit) keeps discount 1, as the release stores it;
- metadata: ``run``, ``seed``, ``checkpoint``, ``episode_index``, ``episode_id`` and
  ``episode_return`` (the sum of the stored rewards, which ``rlu validate`` checks). Atari stores
  the reward the env returns, the raw game score by default (as converted
  ``atari_episodes_ordered`` data does), so ``episode_return`` is the raw score and
  ``clipped_episode_return`` the sum of the rewards clipped to [-1, 1];
- Atari: the env's (84, 84, 4) stack is stored as its newest frame only; the schema stacks
  frames at sample time (zeros before the episode start, exactly what the env's stack holds).

Buffers are allocated once per recorder at the task's episode length and filled in place.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from rlu.data import Schema
from rlu.domains import DOMAINS
from rlu.segments import Segment, make_episode
from rlu.tasks import TaskSpec
from rlu.types import ArraySpec, ObservationSpec, RluError


def episode_id(run: int, episode_index: int) -> int:
    """A dataset-unique id: the run in the high 32 bits, its episode counter in the low ones."""
    return (int(run) << 32) | int(episode_index)


def schema_for(task: TaskSpec) -> Schema:
    """The store schema of generated data for ``task`` (Atari frames stacked at sample time)."""
    return Schema.for_task(task)


class EpisodeRecorder:
    def __init__(
        self,
        task: TaskSpec,
        max_steps: int | None = None,
        observation_spec: ObservationSpec | None = None,
    ):
        """``observation_spec``: what the env returns when it differs from the TaskSpec (RWRL's
        easy challenge adds dummy keys)."""
        self.task = task
        self.atari = DOMAINS[task.domain].stacked_frames
        self.capacity = int(max_steps or task.episode_length)
        spec = observation_spec if observation_spec is not None else schema_for(task).observation
        n = self.capacity + 1
        if isinstance(spec, ArraySpec):
            self._obs: Any = np.zeros((n, *spec.shape), spec.dtype)
        else:
            self._obs = {k: np.zeros((n, *s.shape), s.dtype) for k, s in spec.items()}
        a = task.action_spec
        self._actions = np.zeros((self.capacity, *a.shape), a.dtype)
        self._rewards = np.zeros(self.capacity, np.float32)
        self._t = -1

    def _put(self, t: int, obs: Any) -> None:
        if self.atari:
            self._obs[t] = obs[..., -1]
        elif isinstance(self._obs, Mapping):
            for k, buf in self._obs.items():
                buf[t] = obs[k]
        else:
            self._obs[t] = obs

    def begin(self, observation: Any) -> None:
        self._t = 0
        self._put(0, observation)

    def step(
        self,
        action: Any,
        reward: float,
        observation: Any,
        terminated: bool,
        truncated: bool,
        info: Mapping[str, Any] | None = None,
        metadata: Mapping[str, Any] | None = None,
    ) -> Segment | None:
        """Record one transition; returns the episode's segment when it ended, else None."""
        t = self._t
        if t < 0:
            raise RluError("EpisodeRecorder.step before begin(); call begin(obs) after env.reset()")
        if t >= self.capacity:
            raise RluError(
                f"{self.task.id}: episode longer than the recorder's {self.capacity} steps; "
                "pass max_steps= the env's time limit"
            )
        self._actions[t] = action
        self._rewards[t] = reward
        self._t = t = t + 1
        self._put(t, observation)
        if not (terminated or truncated or t == self.capacity):
            return None
        return self._finish(bool(terminated), metadata or {})

    def _finish(self, terminal: bool, metadata: Mapping[str, Any]) -> Segment:
        n = self._t
        self._t = -1
        if isinstance(self._obs, Mapping):
            obs: Any = {k: v[: n + 1].copy() for k, v in self._obs.items()}
        else:
            obs = self._obs[: n + 1].copy()
        meta = dict(metadata)
        prefix = None
        if self.atari:
            clipped = np.clip(self._rewards[:n], -1.0, 1.0)
            meta["clipped_episode_return"] = float(clipped.sum(dtype=np.float64))
            prefix = np.zeros((schema_for(self.task).frame_stack - 1, *obs.shape[1:]), np.uint8)
        return make_episode(
            obs, self._actions[:n].copy(), self._rewards[:n].copy(), terminal, meta, prefix
        )


def record_policy(
    env: Any,
    policy: Any,
    recorder: EpisodeRecorder,
    seed: int,
    metadata: Mapping[str, Any] | None = None,
) -> Segment:
    """One episode of ``policy(observation) -> action`` in ``env`` (reset with ``seed``)."""
    obs, _ = env.reset(seed=int(seed))
    recorder.begin(obs)
    while True:
        action = policy(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        seg = recorder.step(action, reward, obs, terminated, truncated, info, metadata)
        if seg is not None:
            return seg
