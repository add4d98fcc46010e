"""Vectorised evaluation rollouts: ``num_envs`` Gymnasium envs stepped in lockstep, one batched
policy call per step. The policy sees observations, episode starts and the previous rewards
only (a ``rlu.types.Policy`` callable, never the agent): every call has one row per env, in the
same order (an env with no episode left keeps its last observation and its action is dropped),
``is_first`` marks the rows whose episode starts there, so recurrent policies keep their state
per row and restart it with each episode, and ``reward`` holds what each row's previous action
earned (0 where ``is_first``), which a return-conditioned policy subtracts from its return to go.

Episode ``i`` is reset with seed ``episode_seed(seed, i)`` (stream ``i`` spawned from ``seed``
by numpy's SeedSequence, not ``seed + i``, under which evaluation seed 4 replayed episodes 1.. of
seed 3) and runs on whichever env is free, so the returns (listed in episode order) do not
depend on ``num_envs``. Envs come from a factory: any callable
returning a Gymnasium env; ``task_env_factory`` builds ``rlu.envs.make_env`` for a task id.
"""

from __future__ import annotations

import contextlib
import importlib
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from rlu.seeds import derive_seed
from rlu.system import install_hint
from rlu.types import Policy, RluError

EnvFactory = Callable[[], Any]


@dataclass(frozen=True)
class EvalResult:
    """The outcome of :func:`evaluate`: each episode's return and length, in episode order."""

    returns: tuple[float, ...]
    """Undiscounted return of each episode, in episode order."""
    lengths: tuple[int, ...]
    """Steps of each episode."""

    @property
    def mean(self) -> float:
        """The mean return over the episodes."""
        return float(np.mean(self.returns))

    def to_json(self) -> dict[str, Any]:
        """``{returns, lengths, mean}``: what ``rlu evaluate --json`` prints, eval.jsonl holds."""
        return {"returns": list(self.returns), "lengths": list(self.lengths), "mean": self.mean}


def episode_seed(seed: int, episode: int) -> int:
    """The reset seed of episode ``episode`` of an evaluation seeded with ``seed``."""
    return derive_seed(seed, episode)


_TRUSTED_ENVS: dict[str, Callable[..., Any]] = {}


def trust_env_factory(spec: str) -> Callable[..., Any]:
    """``"package.module:function"`` -> the function (an env factory taking (task_id, seed)),
    imported. Only code and the command line call this: an env factory named in a file (a run's
    config.json) is never imported (``rlu.training.restore``)."""
    if spec in _TRUSTED_ENVS:
        return _TRUSTED_ENVS[spec]
    module, _, attr = spec.partition(":")
    if not module or not attr or not all(p.isidentifier() for p in (*module.split("."), attr)):
        raise RluError(f"env factory {spec!r}; write it as 'package.module:function'")
    try:
        fn = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as e:
        raise RluError(f"env factory {spec!r} cannot be imported: {e}") from None
    if not callable(fn):
        raise RluError(f"env factory {spec!r} is not a function")
    _TRUSTED_ENVS[spec] = fn
    return fn


def task_env_factory(
    task_id: str, make_env: str | Callable[..., Any] | None = None, **kwargs: Any
) -> EnvFactory:
    """A zero-argument factory for ``task_id``'s env: ``rlu.envs.make_env`` unless ``make_env``
    (a callable, or 'module:function' with the same signature, which code or the command line
    named: :func:`trust_env_factory`) is given."""
    if make_env is None:
        try:
            mod = importlib.import_module("rlu.envs")
        except ImportError as e:
            from rlu.domains import DOMAINS

            extras = dict.fromkeys(d.extra for d in DOMAINS.values())  # each once, in order
            raise RluError(
                f"rlu.envs cannot be imported ({e}); install the env extras "
                f"({install_hint(*extras)}) or pass an env factory"
            ) from None
        fn = mod.make_env
    elif isinstance(make_env, str):
        fn = trust_env_factory(make_env)
    else:
        fn = make_env

    def factory() -> Any:
        return fn(task_id, **kwargs)

    return factory


def _stack(obs_list: list[Any]) -> Any:
    if isinstance(obs_list[0], Mapping):
        return {k: np.stack([np.asarray(o[k]) for o in obs_list]) for k in obs_list[0]}
    return np.stack([np.asarray(o) for o in obs_list])


def _inference_mode() -> contextlib.AbstractContextManager:
    """torch.inference_mode when torch is loaded (a torch policy: no autograd records for its
    forward passes), else nothing; evaluation itself never imports torch."""
    torch = sys.modules.get("torch")
    return torch.inference_mode() if torch is not None else contextlib.nullcontext()


class EpisodeObserver(Protocol):
    """What ``evaluate(..., observer=...)`` tells while it plays: each episode's reset and steps,
    on the env that plays it (to film it, ``rlu.evaluation.video.Recorder``, or show progress)."""

    def reset(self, episode: int, env: Any) -> None:
        """Episode ``episode`` was reset on ``env`` (its first observation is there)."""

    def step(self, episode: int, env: Any, reward: float, done: bool) -> None:
        """Episode ``episode`` took a step on ``env`` with ``reward``; ``done``: its last."""


def evaluate(
    policy: Policy,
    env_fn: EnvFactory,
    num_episodes: int = 10,
    seed: int = 0,
    num_envs: int = 4,
    max_steps: int | None = None,
    observer: EpisodeObserver | None = None,
) -> EvalResult:
    """Run ``num_episodes`` episodes of ``policy`` (batched observations, episode starts and the
    rewards of the previous actions -> batched actions).

    ``max_steps`` caps an episode's length on top of the env's own time limit. ``observer``
    hears of every reset and step (:class:`EpisodeObserver`), before the env moves on.
    """
    if num_episodes < 1:
        raise RluError(f"num_episodes={num_episodes}; evaluate at least one episode")
    num_envs = max(1, min(int(num_envs), num_episodes))
    envs = [env_fn() for _ in range(num_envs)]
    returns = np.zeros(num_episodes, np.float64)
    lengths = np.zeros(num_episodes, np.int64)
    episode = [-1] * num_envs  # episode index running on each env (-1: idle)
    obs: list[Any] = [None] * num_envs
    is_first = np.ones(num_envs, bool)
    reward = np.zeros(num_envs, np.float64)  # what each row's previous action earned
    next_episode = 0
    try:
        with _inference_mode():  # the policy runs once per step; no autograd
            for i in range(num_envs):
                obs[i], _ = envs[i].reset(seed=episode_seed(seed, next_episode))
                episode[i] = next_episode
                if observer is not None:
                    observer.reset(next_episode, envs[i])
                next_episode += 1
            while True:
                active = [i for i in range(num_envs) if episode[i] >= 0]
                if not active:
                    break
                actions = np.asarray(policy(_stack(obs), is_first.copy(), reward.copy()))
                is_first[:] = False
                for i in active:
                    o, r, terminated, truncated, _ = envs[i].step(actions[i])
                    e = episode[i]
                    returns[e] += float(r)
                    reward[i] = float(r)
                    lengths[e] += 1
                    if max_steps is not None and lengths[e] >= max_steps:
                        truncated = True
                    if observer is not None:
                        observer.step(e, envs[i], float(r), bool(terminated or truncated))
                    if terminated or truncated:
                        if next_episode < num_episodes:
                            o, _ = envs[i].reset(seed=episode_seed(seed, next_episode))
                            episode[i] = next_episode
                            if observer is not None:
                                observer.reset(next_episode, envs[i])
                            is_first[i] = True
                            reward[i] = 0.0
                            next_episode += 1
                        else:
                            episode[i] = -1
                    obs[i] = o
    finally:
        for env in envs:
            env.close()
    return EvalResult(tuple(float(x) for x in returns), tuple(int(x) for x in lengths))
