"""Every environment of the suite, built from its TaskSpec, configured as the data was recorded.

    env = rlu.make_env("control_suite/cartpole_swingup", seed=0)
    env = rlu.make_env("rwrl/walker_walk", seed=0, challenge="easy")
    env = rlu.make_env("atari/Pong", seed=0)            # (84, 84, 4) uint8, newest frame last
    venv = rlu.envs.make_vector_env("atari/Pong", num_envs=2, seed=0)

Every task is also a Gymnasium id, registered when this package is imported (see
``rlu.envs.registration``): ``gymnasium.make("rlu/control_suite-cartpole_swingup-v0")``, settings
as keyword arguments. ``make_env(...).spec`` is the spec ``gymnasium.make`` would give the same
env, so ``gymnasium.make(env.spec)`` makes it again.

Each factory returns a Gymnasium env whose observations equal the TaskSpec (and so the dataset
schema): a flat dict keyed as the release without its ``observation/`` prefix for the MuJoCo
domains, one uint8 array for Atari. The factory checks the first observation against the spec.
MuJoCo envs also offer ``env.dm_env``, a dm_env view of the same environment.

Every domain takes ``render_mode="rgb_array"`` (``env.render()`` returns the frame; MuJoCo's
offscreen renderer or the ALE's screen, see ``rlu.domains.envkit``), and
``env.spec.max_episode_steps`` is the episode's real step limit. Settings per domain (keyword
arguments of ``make_env``):

- control suite: none.
- locomotion: ``camera`` (default True: the 64x64x3 egocentric camera rendered every step, as
  in the data; False drops it from observations and spec, ~10-40x faster).
- atari: ``max_episode_steps`` (27,000 agent steps = the paper's 108K frames; the original
  evaluation wrapper counted 108,000 agent steps, pass ``ATARI_ORIGINAL_EVAL_STEPS``),
  ``clip_rewards`` (default False: ``r`` is the raw game score, what evaluation sums; the
  agents clip to [-1, 1] when they learn; ``info["raw_reward"]`` always holds the raw score),
  ``sticky_action_prob`` (0.25), ``frame_skip`` (4).
- rwrl: ``challenge`` ("none" or "easy" as released; "medium"/"hard" also exist),
  ``safety`` / ``safety_coeff``, ``multiobj_coeff`` / ``multiobj_reward`` /
  ``multiobj_observed`` (see rlu.domains.rwrl.env).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from rlu.envs.make import make_env

if TYPE_CHECKING:  # pragma: no cover
    import gymnasium

__all__ = ["make_env", "make_vector_env", "gym_id", "ATARI_ORIGINAL_EVAL_STEPS"]

# rl_unplugged/atari.py's evaluation env truncated after 108,000 *wrapper* (agent) steps,
# i.e. 432K frames; rlu's default is the paper's 108K frames = 27,000 agent steps.
ATARI_ORIGINAL_EVAL_STEPS = 108_000
"""The agent steps after which the original rl_unplugged Atari evaluation env truncated (108,000
wrapper steps = 432K frames); ``make_env(..., max_episode_steps=ATARI_ORIGINAL_EVAL_STEPS)``
reproduces it (rlu's default is the paper's 27,000)."""


def gym_id(task_id: str) -> str:
    """The Gymnasium id of ``task_id`` (``rlu/control_suite-cartpole_swingup-v0``)."""
    from rlu.envs.registration import gym_id as _gym_id

    return _gym_id(task_id)


def make_vector_env(
    task_id: str,
    num_envs: int | None = None,
    seed: int | None = None,
    challenge: str | None = None,
    **kwargs: Any,
) -> gymnasium.vector.VectorEnv:
    """N copies of the task stepping in worker processes (see rlu.envs.vector)."""
    from rlu.envs.vector import make_vector_env as _make

    return _make(task_id, num_envs=num_envs, seed=seed, challenge=challenge, **kwargs)


try:  # register the Gymnasium ids; without gymnasium (no env extra) make_env says what to install
    import gymnasium as _gymnasium  # noqa: F401
except ImportError:  # pragma: no cover - exercised only without the extras
    pass
else:
    from rlu.envs.registration import register_envs as _register_envs

    _register_envs()
