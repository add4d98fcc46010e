"""Vectorised evaluation envs: N copies of a task behind Gymnasium's VectorEnv interface.

    venv = make_vector_env("control_suite/walker_walk", num_envs=2, seed=0)
    obs, info = venv.reset()             # dict of (N, ...) arrays, or (N, 84, 84, 4) for Atari
    obs, reward, terminated, truncated, info = venv.step(actions)

Backends (``"auto"`` picks per domain, ``Domain.vector_backend``: ale for Atari, process for
locomotion, sync for the control suite and RWRL, from bench/envs.py):
- ``"process"``: ``ProcessVectorEnv``, N envs over ``num_workers`` (default:
  the available cores) worker processes, each stepping its share of envs in a loop, so one
  message round trip serves N / W env steps. Env i is ``rlu.make_env(task, seed=seed + i)``, so
  every sub-env is exactly the single env of that seed. MuJoCo workers start through
  ``forkserver`` so that no GL context is ever inherited across a fork.
- ``"async"``: ``gymnasium.vector.AsyncVectorEnv``, one process per env (shared-memory
  observations), same seeding.
- ``"ale"`` (Atari default; a domain's native vector env, ``Domain.native_vector``, made by its
  env module's ``make_vector``: ``rlu.domains.atari.env.AleVectorEnv``): ale-py's C++
  ``AtariVectorEnv`` with rlu's settings (sticky 0.25,
  no no-ops, no fire reset, frame skip 4 with max-pool, 84x84 grey, 4 frames zero-padded at an
  episode start, newest last). Its frames were checked to be bit-identical to ``AtariEnv``'s
  under the same actions (tests/envs/test_vector.py); its seeding differs from the single env's,
  so a sub-env is not the single env of some seed. Observations are transposed to (N, 84, 84, 4);
  rewards are the raw game scores, as the single env's (``clip_rewards=True`` clips them;
  ``info["raw_reward"]`` is always raw). It runs its
  own thread pool and measured faster than processes (bench/envs.py).
- ``"sync"``: ``gymnasium.vector.SyncVectorEnv``, the N envs stepped in this process.

All backends use Gymnasium's default autoreset mode (next step): after a sub-env's episode ends,
its next ``step`` ignores the action and returns the first observation of a new episode.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any, Literal, SupportsFloat

import numpy as np

from rlu.domains import DOMAINS
from rlu.domains.envkit import gym
from rlu.system import available_cores
from rlu.tasks import get_task
from rlu.types import RluError

# Chosen by measurement (bench/envs.py; the figures and their machine: bench/README.md, "Design
# choices"): ALE's C++ threads beat processes for Atari; worker processes pay off for the slow
# camera envs of locomotion; control-suite and RWRL steps are cheaper than a message round trip
# to a worker, so their N envs step in this process, where the batched policy forward (PyTorch's
# intra-op threads) is what uses the second core.
_AUTO = {name: d.vector_backend for name, d in DOMAINS.items()}


def _make_one(
    task_id: str, seed: int | None, challenge: str | None, settings: dict[str, Any]
) -> gym.Env:
    from rlu.envs.make import make_env

    return make_env(task_id, seed=seed, challenge=challenge, **settings)


def make_vector_env(
    task_id: str,
    num_envs: int | None = None,
    seed: int | None = None,
    challenge: str | None = None,
    backend: str = "auto",
    num_workers: int | None = None,
    **settings: Any,
) -> gym.vector.VectorEnv:
    """``num_envs`` (default: the available cores) copies of ``task_id``; see the module doc."""
    task = get_task(task_id)
    n = int(num_envs or available_cores())
    if n < 1:
        raise RluError(f"num_envs must be >= 1, got {num_envs}")
    domain = DOMAINS[task.domain]
    if backend == "auto":
        backend = _AUTO[task.domain]
    native = {d.native_vector for d in DOMAINS.values() if d.native_vector is not None}
    if backend in native:
        if backend != domain.native_vector:
            raise RluError(f"{task.id}: backend {backend!r} is another domain's; use 'async'")
        return domain.env_factory().make_vector(task, n, seed, **settings)
    fns = [
        functools.partial(
            _make_one, task_id, None if seed is None else seed + i, challenge, settings
        )
        for i in range(n)
    ]
    if backend == "sync":
        return gym.vector.SyncVectorEnv(fns)
    # forkserver: no MuJoCo GL context is inherited across a fork (a native vector env's domain
    # forks, as before)
    context: Literal["forkserver"] | None = None if domain.native_vector else "forkserver"
    if backend == "process":
        return ProcessVectorEnv(fns, num_workers=num_workers, context=context)
    if backend == "async":
        if num_workers not in (None, n):
            raise RluError("backend 'async' runs one process per env; drop num_workers")
        return gym.vector.AsyncVectorEnv(fns, context=context)
    names = ", ".join(["auto", "process", "async", *sorted(native), "sync"])
    raise RluError(f"unknown vector backend {backend!r}; use {names}")


def _stack(items: list) -> Any:
    if isinstance(items[0], dict):
        return {k: np.stack([x[k] for x in items]) for k in items[0]}
    return np.stack(items)


def _merge_infos(infos: list[dict]) -> dict[str, np.ndarray]:
    keys = set(infos[0]).intersection(*infos[1:]) if len(infos) > 1 else set(infos[0])
    return {k: np.array([i[k] for i in infos]) for k in sorted(keys)}


def _worker(conn: Connection, fns: Sequence[Callable[[], gym.Env]]) -> None:
    envs = [fn() for fn in fns]
    done = [False] * len(envs)
    try:
        while True:
            cmd, data = conn.recv()
            if cmd == "reset":
                out = [e.reset(seed=s) for e, s in zip(envs, data, strict=True)]
                done = [False] * len(envs)
                conn.send((_stack([o for o, _ in out]), [i for _, i in out]))
            elif cmd == "step":
                obs, rew, term, trunc, infos = [], [], [], [], []
                for j, (e, a) in enumerate(zip(envs, data, strict=True)):
                    r: SupportsFloat
                    if done[j]:  # Gymnasium's next-step autoreset: the action is ignored
                        o, i = e.reset()
                        r, te, tr = 0.0, False, False
                    else:
                        o, r, te, tr, i = e.step(a)
                    done[j] = te or tr
                    obs.append(o)
                    rew.append(r)
                    term.append(te)
                    trunc.append(tr)
                    infos.append(i)
                conn.send((_stack(obs), np.array(rew), np.array(term), np.array(trunc), infos))
            elif cmd == "close":
                break
    except (EOFError, KeyboardInterrupt):
        pass
    finally:
        for e in envs:
            e.close()
        conn.close()


class ProcessVectorEnv(gym.vector.VectorEnv):
    """N envs spread over W worker processes, each stepping its share in a loop.

    Unlike ``AsyncVectorEnv`` (one process per env) a worker holds several envs, so one message
    round trip serves N / W env steps: for fast envs (control suite, thousands of steps/s) the
    inter-process cost is paid once per worker instead of once per env. Env i keeps its own
    seed; autoreset is Gymnasium's next-step mode.
    """

    def __init__(
        self,
        env_fns: Sequence[Callable[[], gym.Env]],
        num_workers: int | None = None,
        context: Literal["spawn", "fork", "forkserver"] | None = None,
    ):
        import multiprocessing as mp

        self.num_envs = len(env_fns)
        w = max(1, min(int(num_workers or available_cores()), self.num_envs))
        bounds = np.linspace(0, self.num_envs, w + 1).astype(int)
        self._slices = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
        probe = env_fns[0]()
        self.single_observation_space = probe.observation_space
        self.single_action_space = probe.action_space
        probe.close()
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, self.num_envs
        )
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self.metadata = {"autoreset_mode": gym.vector.AutoresetMode.NEXT_STEP}
        ctx = mp.get_context(context)
        self._conns, self._procs = [], []
        for sl in self._slices:
            parent, child = ctx.Pipe()
            p = ctx.Process(target=_worker, args=(child, env_fns[sl]), daemon=True)
            p.start()
            child.close()
            self._conns.append(parent)
            self._procs.append(p)
        self._closed = False

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, np.ndarray]]:
        seeds = [None] * self.num_envs if seed is None else [seed + i for i in range(self.num_envs)]
        for c, sl in zip(self._conns, self._slices, strict=True):
            c.send(("reset", seeds[sl]))
        parts = [c.recv() for c in self._conns]
        obs = _concat([p[0] for p in parts])
        return obs, _merge_infos([i for p in parts for i in p[1]])

    def step(
        self, actions: Any
    ) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        actions = np.asarray(actions) if not isinstance(actions, dict) else actions
        for c, sl in zip(self._conns, self._slices, strict=True):
            c.send(("step", list(actions[sl])))
        parts = [c.recv() for c in self._conns]
        obs = _concat([p[0] for p in parts])
        rew, term, trunc = (np.concatenate([p[k] for p in parts]) for k in (1, 2, 3))
        return obs, rew, term, trunc, _merge_infos([i for p in parts for i in p[4]])

    def close(self, **kwargs: Any) -> None:
        if self._closed:
            return
        self._closed = True
        for c in self._conns:
            try:
                c.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for p in self._procs:
            p.join(timeout=10)
            if p.is_alive():
                p.terminate()


def _concat(parts: list) -> Any:
    if isinstance(parts[0], dict):
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return np.concatenate(parts)
