"""Atari 2600 through the ALE, preprocessed as the RL Unplugged data was recorded.

The data came from Dopamine's DQN with sticky actions (``rl_unplugged/atari.py`` evaluates with
``dopamine.discrete_domains.atari_lib.create_atari_environment(game, sticky_actions=True)``).
This env re-implements Dopamine's ``AtariPreprocessing`` directly over ``ale_py.ALEInterface``:

- sticky actions with probability 0.25, applied by the ALE on every frame (Machado et al. 2018);
- minimal action set; no no-op starts; no fire on reset; terminal on game over, not life loss;
- frame skip 4: the agent's action is repeated for 4 frames, the rewards summed, and the
  observation is the pixel-wise max of the grey-scale screens of the last two frames, resized
  to 84x84 with ``cv2.INTER_AREA`` (Dopamine's ``_pool_and_resize``). If the game ends inside
  the skip, the loop stops and the pooled screens are whatever the buffers hold, as Dopamine;
- 4 stacked frames, newest last, shape (84, 84, 4) uint8; at an episode start the stack holds
  zero frames before the first frame, as Dopamine's agent state and replay (which produced the
  data) do;
- reward: ``step`` returns the raw game score of the step (the sum over the skipped frames), so
  every evaluation path (``rlu.evaluation.rollout.evaluate`` and all that calls it) sums the
  score the paper reports and the random scores hold. Learning uses rewards clipped to [-1, 1]
  (the paper's Table "Atari 2600 Environment Details"; Dopamine's runner clips before storing a
  transition): the discrete agents clip at learning time, so the same stored raw rewards train
  the same whatever their source. ``clip_rewards=True`` returns the clipped reward instead, for
  code that wants Dopamine's online loop as is; ``info["raw_reward"]`` always holds the raw score;
- episode cap: ``max_episode_steps`` agent steps, then ``truncated=True``. The default 27,000
  agent steps = 108,000 frames is the paper's and Dopamine's cap. The original RLU evaluation
  wrapper truncated after 108,000 *agent* steps (432K frames);
  ``max_episode_steps=rlu.envs.ATARI_ORIGINAL_EVAL_STEPS`` gives that.

Rendering: ``render_mode="rgb_array"`` makes ``render()`` return the ALE's full-colour screen,
(210, 160, 3) uint8, of the last emulated frame (what a player sees; the observation is its
pooled grey 84x84 version), at 60 / frame_skip = 15 frames per second, one per agent step.

Seeding follows ale_py's own env: ``SeedSequence(seed)`` gives the ALE's ``random_seed`` (which
drives sticky actions) and the ROM is reloaded; ``reset(seed=s)`` is ``make_env(seed=s).reset()``.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from rlu.domains.atari import ATARI_MAX_AGENT_STEPS
from rlu.domains.envkit import (
    RENDER_MODES,
    Render,
    check_observation,
    gym,
    observation_space,
    spaces,
)
from rlu.domains.spec import TaskSpec
from rlu.system import available_cores
from rlu.types import RluError

SCREEN_SIZE = 84
STICKY_ACTION_PROB = 0.25
FRAME_SKIP = 4
ALE_FPS = 60  # the Atari 2600's NTSC frame rate


def rom_id(game: str) -> str:
    """ale_py's snake_case ROM id of a PascalCase game name (MsPacman -> ms_pacman)."""
    return re.sub(r"(?<!^)(?=[A-Z])", "_", game).lower()


class AtariEnv(gym.Env):
    """One Atari game with Dopamine's preprocessing; see the module docstring."""

    metadata = {"render_modes": list(RENDER_MODES), "render_fps": ALE_FPS / FRAME_SKIP}
    action_space: spaces.Discrete

    def __init__(
        self,
        game: str,
        seed: int | None = None,
        *,
        max_episode_steps: int = ATARI_MAX_AGENT_STEPS,
        clip_rewards: bool = False,
        sticky_action_prob: float = STICKY_ACTION_PROB,
        frame_skip: int = FRAME_SKIP,
        frame_stack: int = 4,
        render_mode: str | None = None,
    ) -> None:
        import ale_py
        import cv2

        if frame_skip < 2:
            raise RluError(f"atari/{game}: frame_skip must be >= 2 (max-pool of two frames)")
        self._cv2 = cv2
        self.game = game
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": ALE_FPS / frame_skip}
        rom = ale_py.roms.get_rom_path(rom_id(game))
        if rom is None:
            raise RluError(f"atari/{game}: ale-py has no ROM {rom_id(game)!r}")
        self._rom = rom
        self.ale = ale_py.ALEInterface()
        self.ale.setLoggerMode(ale_py.LoggerMode.Error)
        self.ale.setFloat("repeat_action_probability", float(sticky_action_prob))
        self._seed_ale(seed)
        self._actions = list(self.ale.getMinimalActionSet())
        self.action_space = spaces.Discrete(len(self._actions))
        self.max_episode_steps = int(max_episode_steps)
        self.clip_rewards = bool(clip_rewards)
        self.frame_skip = int(frame_skip)
        from rlu.types import ArraySpec

        self._spec = ArraySpec((SCREEN_SIZE, SCREEN_SIZE, frame_stack), "uint8")
        self.observation_space = observation_space(self._spec)
        h, w = self.ale.getScreenDims()
        self._screens = np.zeros((2, h, w), np.uint8)
        self._stack = np.zeros(self._spec.shape, np.uint8)
        self._steps = 0

    def _seed_ale(self, seed: int | None) -> None:
        ss = np.random.SeedSequence(seed)
        _, ale_seed = ss.generate_state(n_words=2)
        self.ale.setInt("random_seed", int(np.int32(ale_seed)))
        self.ale.loadROM(self._rom)

    def _pool_and_resize(self) -> np.ndarray:
        np.maximum(self._screens[0], self._screens[1], out=self._screens[0])
        return self._cv2.resize(
            self._screens[0], (SCREEN_SIZE, SCREEN_SIZE), interpolation=self._cv2.INTER_AREA
        )

    def _push(self, frame: np.ndarray) -> np.ndarray:
        self._stack[:, :, :-1] = self._stack[:, :, 1:]
        self._stack[:, :, -1] = frame
        return self._stack.copy()

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        if seed is not None:
            self._seed_ale(int(seed))
        self.ale.reset_game()
        self._steps = 0
        self.ale.getScreenGrayscale(self._screens[0])
        self._screens[1].fill(0)
        self._stack.fill(0)
        obs = self._push(self._pool_and_resize())
        return obs, {"raw_reward": 0.0, "lives": self.ale.lives()}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        a = self._actions[int(action)]
        ale = self.ale
        reward = 0.0
        game_over = False
        skip = self.frame_skip
        for t in range(skip):
            reward += ale.act(a)
            if ale.game_over():
                game_over = True
                break
            if t >= skip - 2:
                ale.getScreenGrayscale(self._screens[t - (skip - 2)])
        obs = self._push(self._pool_and_resize())
        self._steps += 1
        truncated = not game_over and self._steps >= self.max_episode_steps
        out = max(-1.0, min(1.0, reward)) if self.clip_rewards else reward
        return obs, out, game_over, truncated, {"raw_reward": reward, "lives": ale.lives()}

    def render(self) -> np.ndarray:
        """The ALE's colour screen of the last emulated frame, (210, 160, 3) uint8."""
        if self.render_mode is None:
            raise RluError(
                f"atari/{self.game}: render() needs the env made with render_mode='rgb_array' "
                "(rlu.make_env(..., render_mode='rgb_array') or gymnasium.make(..., same))"
            )
        return self.ale.getScreenRGB()

    def check(self) -> None:
        check_observation(self._stack, self._spec, f"atari/{self.game}")


def make(
    task: TaskSpec, seed: int | None = None, render: Render | None = None, **settings: Any
) -> AtariEnv:
    allowed = {"max_episode_steps", "clip_rewards", "sticky_action_prob", "frame_skip"}
    if set(settings) - allowed:
        raise RluError(
            f"{task.id}: unknown env settings {sorted(set(settings) - allowed)}; "
            f"Atari takes {sorted(allowed)}"
        )
    render = render or Render()
    if render.size is not None or render.camera is not None:
        raise RluError(
            f"{task.id}: render_size / render_camera are MuJoCo settings; Atari renders the "
            "ALE's own 210x160 screen"
        )
    env = AtariEnv(task.env["game"], seed, render_mode=render.mode, **settings)
    env.check()
    if env.action_space.n != task.action_dim:
        raise RluError(
            f"{task.id}: ALE's minimal action set has {env.action_space.n} actions, the TaskSpec "
            f"says {task.action_dim}; rlu/tasks.py ATARI_NUM_ACTIONS needs updating"
        )
    if env.observation_space != observation_space(task.observation_spec):
        raise RluError(f"{task.id}: the env's observation space differs from the TaskSpec")
    return env


# --- the native vector env (``rlu.envs.make_vector_env``'s "ale" backend) -----------------------


def make_vector(task: TaskSpec, num_envs: int, seed: int | None = None, **settings: Any) -> Any:
    """``num_envs`` copies of ``task`` in ale-py's C++ vector env (see :class:`AleVectorEnv`)."""
    return AleVectorEnv(task.env["game"], num_envs, seed, **settings)


def _frames_last(obs: np.ndarray) -> np.ndarray:
    """(N, 4, 84, 84) -> a new contiguous (N, 84, 84, 4) array.

    One strided copy per frame plane, faster than ``ascontiguousarray(transpose)`` for uint8
    by enough to matter beside ALE's own step (bench/README.md, "Design choices").
    """
    out = np.empty((obs.shape[0], *obs.shape[2:], obs.shape[1]), obs.dtype)
    for c in range(obs.shape[1]):
        out[..., c] = obs[:, c]
    return out


class AleVectorEnv(gym.vector.VectorEnv):
    """ale-py's AtariVectorEnv with rlu's observation layout and reward convention."""

    def __init__(
        self,
        game: str,
        num_envs: int,
        seed: int | None = None,
        *,
        max_episode_steps: int = ATARI_MAX_AGENT_STEPS,
        clip_rewards: bool = False,
        sticky_action_prob: float = 0.25,
        frame_skip: int = 4,
        num_threads: int | None = None,
    ) -> None:
        from ale_py.vector_env import AtariVectorEnv

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
        space = self._env.single_action_space
        assert isinstance(space, spaces.Discrete)  # ALE's minimal action set
        n_actions = space.n
        self.single_observation_space = spaces.Box(0, 255, (SCREEN_SIZE, SCREEN_SIZE, 4), np.uint8)
        self.single_action_space = spaces.Discrete(n_actions)
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, num_envs
        )
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self.metadata = {"autoreset_mode": gym.vector.AutoresetMode.NEXT_STEP}

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is None and self._seed is not None:
            seed, self._seed = self._seed, None  # the constructor's seed seeds the first reset
        obs, info = self._env.reset(seed=seed, options=options)
        return _frames_last(obs), info

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, Any, Any, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self._env.step(np.asarray(actions))
        raw = np.asarray(reward, np.float64)
        info = dict(info)
        info["raw_reward"] = raw
        out = np.clip(raw, -1.0, 1.0) if self.clip_rewards else raw
        return _frames_last(obs), out, terminated, truncated, info

    def close(self, **kwargs: Any) -> None:
        self._env.close()
