"""Pieces every rlu env shares: spec -> Gymnasium space, the dm_env -> Gymnasium adapter.

The adapter is the only per-step Python between an agent and dm_control. It does what the
original RL Unplugged wrappers did (``rl_unplugged/dm_control_suite.py``: action normalisation
to [-1, 1] -> clip -> float32 -> keep the dataset's observation keys) and nothing more:

- observations: a flat dict keyed as the release (``position``, ``walker/joints_pos``), each
  array cast to the TaskSpec dtype and reshaped to its shape (scalars become shape (1,));
- actions: float32 in [-1, 1], clipped, then mapped affinely onto the physics' bounds (the
  identity for every control-suite and RWRL task, whose bounds are already [-1, 1]);
- ``terminated`` when dm_env ends an episode with discount 0, ``truncated`` when it ends with a
  non-zero discount (the time limit). ``info["discount"]`` carries dm_env's discount.

``env.dm_env`` is a dm_env view of the same processed environment (same observations, same
action convention) for code written against dm_env.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from rlu.types import ArraySpec, BoundedSpec, DiscreteSpec, SpecError, install_hint

try:  # gymnasium is in every env extra; rlu.envs is never imported by the numpy-only core.
    import gymnasium as gym
    from gymnasium import spaces
except ImportError as e:  # pragma: no cover - exercised only without the extras
    raise ImportError(
        f"rlu.envs needs gymnasium; install an env extra: {install_hint('control')} "
        "(or locomotion, atari)"
    ) from e


def array_space(spec: ArraySpec) -> spaces.Space:
    """The Gymnasium space of one array spec (uint8 images in [0, 255], features unbounded)."""
    if isinstance(spec, DiscreteSpec):
        return spaces.Discrete(spec.num_values)
    if isinstance(spec, BoundedSpec):
        return spaces.Box(spec.minimum, spec.maximum, spec.shape, np.dtype(spec.dtype))
    dtype = np.dtype(spec.dtype)
    if dtype == np.uint8:
        return spaces.Box(0, 255, spec.shape, np.uint8)
    if dtype == np.bool_:
        return spaces.MultiBinary(spec.shape)
    return spaces.Box(-np.inf, np.inf, spec.shape, dtype)


def observation_space(spec: ArraySpec | Mapping[str, ArraySpec]) -> spaces.Space:
    if isinstance(spec, ArraySpec):
        return array_space(spec)
    return spaces.Dict({k: array_space(v) for k, v in spec.items()})


def check_observation(obs: Any, spec: ArraySpec | Mapping[str, ArraySpec], where: str) -> None:
    """Raise SpecError unless ``obs`` has exactly the keys, shapes and dtypes of ``spec``."""
    if isinstance(spec, ArraySpec):
        _check_array(obs, spec, where)
        return
    if not isinstance(obs, Mapping):
        raise SpecError(f"{where}: observation is {type(obs).__name__}, the spec wants a dict")
    if set(obs) != set(spec):
        missing, extra = sorted(set(spec) - set(obs)), sorted(set(obs) - set(spec))
        raise SpecError(
            f"{where}: observation keys differ from the TaskSpec (missing {missing}, extra "
            f"{extra}); the env builder and rlu/tasks.py must agree"
        )
    for k, s in spec.items():
        _check_array(obs[k], s, f"{where}[{k!r}]")


def _check_array(x: Any, spec: ArraySpec, where: str) -> None:
    if not isinstance(x, np.ndarray) or x.shape != spec.shape or x.dtype != np.dtype(spec.dtype):
        got = (getattr(x, "shape", None), getattr(x, "dtype", type(x).__name__))
        raise SpecError(f"{where}: got shape/dtype {got}, the TaskSpec says {spec}")


class DmControlEnv(gym.Env):
    """A Gymnasium env over a dm_env environment with the release's observation layout.

    ``keys`` maps each observation key of the spec to the key dm_env uses for it (the same for
    every rlu task; kept as a map so that a builder may rename). ``reseed(seed)`` must make the
    wrapped environment's next ``reset()`` a function of ``seed`` only.
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        environment: Any,
        obs_spec: Mapping[str, ArraySpec],
        reseed: Callable[[int], None],
        *,
        name: str = "",
        keys: Mapping[str, str] | None = None,
    ) -> None:
        self._env = environment
        self._spec = dict(obs_spec)
        self._keys = [(k, (keys or {}).get(k, k)) for k in self._spec]
        self._shapes = {k: (s.shape, np.dtype(s.dtype)) for k, s in self._spec.items()}
        self._reseed = reseed
        self._name = name or type(environment).__name__
        self.observation_space = observation_space(self._spec)
        a = environment.action_spec()
        self._num_actions = int(np.prod(a.shape))
        self.action_space = spaces.Box(-1.0, 1.0, a.shape, np.float32)
        lo = np.broadcast_to(np.asarray(a.minimum, np.float64), a.shape)
        hi = np.broadcast_to(np.asarray(a.maximum, np.float64), a.shape)
        if np.all(lo == -1.0) and np.all(hi == 1.0):
            self._scale = None  # the identity: skip two array ops per step
        else:
            # rl_unplugged NormilizeActionSpecWrapper: a_env = (a + 1) / 2 * (max - min) + min.
            self._scale = (hi - lo, lo)
        self._action_dtype = np.dtype(a.dtype)
        self._checked = False

    # --- processing (shared with the dm_env view) ---------------------------------------
    def _observation(self, raw: Mapping[str, Any]) -> dict[str, np.ndarray]:
        out = {}
        shapes = self._shapes
        for k, rk in self._keys:
            shape, dtype = shapes[k]
            x = np.asarray(raw[rk], dtype=dtype)
            out[k] = x if x.shape == shape else x.reshape(shape)
        return out

    def _action(self, action: Any) -> np.ndarray:
        # Two ufuncs: np.clip's Python-level dispatch costs more than the rest of this method.
        a = np.minimum(np.maximum(np.asarray(action, dtype=np.float64), -1.0), 1.0)
        if a.shape != self.action_space.shape:
            a = a.reshape(self.action_space.shape)
        if self._scale is not None:
            a = (a + 1.0) * 0.5 * self._scale[0] + self._scale[1]
        return a

    def _first(self, raw: Mapping[str, Any]) -> dict[str, np.ndarray]:
        try:
            obs = self._observation(raw)
        except KeyError as e:
            raise SpecError(
                f"{self._name}: the environment has no observation {e}; it has "
                f"{sorted(raw)}. rlu/tasks.py and the env builder disagree"
            ) from e
        except ValueError as e:
            raise SpecError(
                f"{self._name}: an observation does not fit its TaskSpec shape: {e}"
            ) from e
        if not self._checked:
            check_observation(obs, self._spec, self._name)
            self._checked = True
        return obs

    # --- Gymnasium API ---------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._reseed(int(seed))
        ts = self._env.reset()
        return self._first(ts.observation), {}

    def step(self, action: Any):
        ts = self._env.step(self._action(action))
        obs = self._observation(ts.observation)
        reward = float(ts.reward) if ts.reward is not None else 0.0
        discount = float(ts.discount) if ts.discount is not None else 1.0
        last = ts.last()
        terminated = bool(last and discount == 0.0)
        return obs, reward, terminated, bool(last and not terminated), {"discount": discount}

    def close(self) -> None:
        close = getattr(self._env, "close", None)
        if close is not None:
            close()

    @property
    def raw_env(self) -> Any:
        """The wrapped dm_control environment (no rlu processing)."""
        return self._env

    @property
    def dm_env(self) -> Any:
        """A dm_env.Environment view with rlu's observations and [-1, 1] actions."""
        return DmEnvView(self)


class DmEnvView:
    """dm_env.Environment interface over a DmControlEnv (shares its state)."""

    def __init__(self, env: DmControlEnv) -> None:
        import dm_env
        from dm_env import specs

        self._gym = env
        self._dm_env = dm_env
        self._specs = specs

    def reset(self):
        ts = self._gym._env.reset()
        return ts._replace(observation=self._gym._first(ts.observation))

    def step(self, action):
        ts = self._gym._env.step(self._gym._action(action))
        obs = self._gym._observation(ts.observation)
        return ts._replace(observation=obs)

    def observation_spec(self):
        return {
            k: self._specs.Array(s.shape, np.dtype(s.dtype), name=k)
            for k, s in self._gym._spec.items()
        }

    def action_spec(self):
        shape = self._gym.action_space.shape
        return self._specs.BoundedArray(shape, np.float32, -1.0, 1.0, name="action")

    def reward_spec(self):
        return self._gym._env.reward_spec()

    def discount_spec(self):
        return self._gym._env.discount_spec()

    def close(self) -> None:
        self._gym.close()
