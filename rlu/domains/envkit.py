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

Rendering (every domain): ``make_env(task, render_mode="rgb_array")`` makes ``env.render()`` return
the current frame as a (H, W, 3) uint8 array, what Gymnasium's ``RecordVideo`` and
``rlu.evaluation.video`` record. MuJoCo envs draw through dm_control's offscreen
``physics.render`` (``MUJOCO_GL=egl`` on a headless machine); ``render_size=(height, width)``
(default 480x640, MuJoCo's offscreen framebuffer) and ``render_camera`` (a camera name or index
of the model) choose the view. ``env.metadata["render_fps"]`` is the real-time rate, one frame
per agent step.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from rlu.system import install_hint
from rlu.types import ArraySpec, BoundedSpec, DiscreteSpec, RluError, SpecError

try:  # gymnasium is in every env extra; rlu.envs is never imported by the numpy-only core.
    import gymnasium as gym
    from gymnasium import spaces
except ImportError as e:  # pragma: no cover - exercised only without the extras
    raise ImportError(
        f"rlu.envs needs gymnasium; install an env extra: {install_hint('control')} "
        "(or locomotion, atari)"
    ) from e


RENDER_MODES = ("rgb_array",)
RENDER_SIZE = (480, 640)
"""Default (height, width) of a MuJoCo frame: the models' offscreen framebuffer (640x480)."""


@dataclass(frozen=True)
class Render:
    """How an env renders: ``make_env``'s ``render_mode`` / ``render_size`` / ``render_camera``."""

    mode: str | None = None
    """None (no frames; ``render()`` refuses) or ``"rgb_array"``."""
    size: tuple[int, int] | None = None
    """(height, width) of a MuJoCo frame; None: ``RENDER_SIZE``. Atari frames are the ALE's."""
    camera: str | int | None = None
    """A MuJoCo camera name or index; None: the domain's default view."""


def render_settings(
    where: str,
    render_mode: str | None = None,
    render_size: Any = None,
    render_camera: str | int | None = None,
) -> Render:
    """Checked render settings of ``make_env`` (``where`` names the task in errors)."""
    if render_mode not in (None, *RENDER_MODES):
        raise RluError(
            f"{where}: render_mode={render_mode!r} is not offered; rlu envs render "
            "'rgb_array' (each frame an (H, W, 3) uint8 array) or nothing (None)"
        )
    size = None
    if render_size is not None:
        try:
            h, w = (int(x) for x in render_size)
        except (TypeError, ValueError):
            raise RluError(
                f"{where}: render_size={render_size!r}; give (height, width), e.g. (480, 640)"
            ) from None
        if h < 1 or w < 1:
            raise RluError(f"{where}: render_size={render_size!r} must be positive")
        size = (h, w)
    if render_mode is None and (size is not None or render_camera is not None):
        raise RluError(f"{where}: render_size / render_camera need render_mode='rgb_array'")
    return Render(render_mode, size, render_camera)


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
    wrapped environment's next ``reset()`` a function of ``seed`` only. ``physics()`` returns
    the MuJoCo physics being stepped now (a locomotion env rebuilds it on a seeded reset), whose
    ``render`` draws the frames; ``control_timestep`` (seconds per agent step) sets the frame
    rate; ``camera`` is the default render view.
    """

    metadata = {"render_modes": list(RENDER_MODES)}  # each env adds its render_fps

    def __init__(
        self,
        environment: Any,
        obs_spec: Mapping[str, ArraySpec],
        reseed: Callable[[int], None],
        *,
        physics: Callable[[], Any],
        control_timestep: float,
        name: str = "",
        keys: Mapping[str, str] | None = None,
        render: Render | None = None,
        camera: str | int = 0,
    ) -> None:
        render = render or Render()
        self._env = environment
        self._physics = physics
        self._closed = False
        self.render_mode = render.mode
        self.metadata = {**self.metadata, "render_fps": 1.0 / float(control_timestep)}
        self._render_size = render.size or RENDER_SIZE
        self._camera = render.camera if render.camera is not None else camera
        if render.mode is not None:
            try:
                self._check_view(name or type(environment).__name__)
            except RluError:
                environment.close()  # built already: free its physics before refusing
                raise
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
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        if seed is not None:
            self._reseed(int(seed))
        ts = self._env.reset()
        return self._first(ts.observation), {}

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        ts = self._env.step(self._action(action))
        obs = self._observation(ts.observation)
        reward = float(ts.reward) if ts.reward is not None else 0.0
        discount = float(ts.discount) if ts.discount is not None else 1.0
        last = ts.last()
        terminated = bool(last and discount == 0.0)
        return obs, reward, terminated, bool(last and not terminated), {"discount": discount}

    def render(self) -> np.ndarray:
        """The current frame, (H, W, 3) uint8, drawn offscreen by MuJoCo."""
        if self.render_mode is None:
            raise RluError(
                f"{self._name}: render() needs the env made with render_mode='rgb_array' "
                "(rlu.make_env(..., render_mode='rgb_array') or gymnasium.make(..., same))"
            )
        h, w = self._render_size
        return self._physics().render(h, w, camera_id=self._camera)

    def _check_view(self, name: str) -> None:
        """Refuse a camera the model lacks or a frame larger than its offscreen buffer now,
        not at the first render() of a long rollout."""
        model = self._physics().model
        cameras = [model.id2name(i, "camera") for i in range(model.ncam)]
        cam = self._camera
        if isinstance(cam, str) and cam not in cameras:
            raise RluError(f"{name}: no camera {cam!r}; the model has {cameras} (or an index)")
        if not isinstance(cam, str) and not -1 <= int(cam) < len(cameras):
            raise RluError(
                f"{name}: camera index {cam} out of range; the model has {len(cameras)} "
                f"cameras {cameras} (-1: the free camera)"
            )
        g = model.vis.global_
        h, w = self._render_size
        if h > g.offheight or w > g.offwidth:
            raise RluError(
                f"{name}: render_size=({h}, {w}) exceeds the model's offscreen framebuffer "
                f"({g.offheight}, {g.offwidth}); pick a smaller one"
            )

    def close(self) -> None:
        """Release the physics and its GL context; a second call does nothing."""
        if self._closed:
            return
        self._closed = True
        self._env.close()

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

    def reset(self) -> Any:
        ts = self._gym._env.reset()
        return ts._replace(observation=self._gym._first(ts.observation))

    def step(self, action: Any) -> Any:
        ts = self._gym._env.step(self._gym._action(action))
        obs = self._gym._observation(ts.observation)
        return ts._replace(observation=obs)

    def observation_spec(self) -> dict[str, Any]:
        return {
            k: self._specs.Array(s.shape, np.dtype(s.dtype), name=k)
            for k, s in self._gym._spec.items()
        }

    def action_spec(self) -> Any:
        shape = self._gym.action_space.shape
        return self._specs.BoundedArray(shape, np.float32, -1.0, 1.0, name="action")

    def reward_spec(self) -> Any:
        return self._gym._env.reward_spec()

    def discount_spec(self) -> Any:
        return self._gym._env.discount_spec()

    def close(self) -> None:
        self._gym.close()
