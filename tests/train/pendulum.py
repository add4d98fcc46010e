"""Real Gymnasium envs for the training-loop tests: Pendulum-v1 with dict observations (like the
control suite's), 50-step episodes, and a dataset recorded from a noisy PD controller in it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rlu.data.store import DatasetWriter, Schema
from rlu.segments import make_episode
from rlu.types import ArraySpec, BoundedSpec

EPISODE_STEPS = 50
GRAVITY = {"test/pendulum": 10.0, "test/pendulum_heavy": 12.0}
OBS_SPEC = {"orientation": ArraySpec((2,), "float32"), "velocity": ArraySpec((1,), "float32")}
ACTION_SPEC = BoundedSpec((1,), "float32", -2.0, 2.0)


def make_env(
    task_id: str,
    seed: int | None = None,
    challenge: str = "none",
    episode_steps: int = EPISODE_STEPS,
):
    import gymnasium as gym

    if task_id not in GRAVITY:
        raise ValueError(f"unknown test task {task_id!r}; use one of {sorted(GRAVITY)}")

    class DictObs(gym.ObservationWrapper):
        def __init__(self, env):
            super().__init__(env)
            self.observation_space = gym.spaces.Dict(
                {
                    "orientation": gym.spaces.Box(-1, 1, (2,), np.float32),
                    "velocity": gym.spaces.Box(-8, 8, (1,), np.float32),
                }
            )

        def observation(self, obs):
            return {
                "orientation": np.asarray(obs[:2], np.float32),
                "velocity": np.asarray(obs[2:], np.float32),
            }

    env = gym.make("Pendulum-v1", g=GRAVITY[task_id], max_episode_steps=episode_steps)
    env = DictObs(env)
    if seed is not None:
        env.reset(seed=seed)
    return env


def write_dataset(dest: Path, task_id: str, episodes: int = 20, seed: int = 0) -> Path:
    """Episodes of a noisy PD controller (towards upright) recorded in the real env."""
    rng = np.random.default_rng(seed)
    env = make_env(task_id)
    schema = Schema(OBS_SPEC, ACTION_SPEC, task_id=task_id)
    with DatasetWriter(dest, schema, {"source": "test", "behaviour": "noisy PD"}) as w:
        for i in range(episodes):
            obs, _ = env.reset(seed=seed * 1000 + i)
            obs_list, acts, rews = [obs], [], []
            done = False
            while not done:
                cos, sin = obs["orientation"]
                th, thdot = np.arctan2(sin, cos), obs["velocity"][0]
                a = np.clip(-(6.0 * th + 1.5 * thdot) + rng.normal(0, 0.7), -2, 2)
                obs, r, term, trunc, _ = env.step(np.array([a], np.float32))
                obs_list.append(obs)
                acts.append([a])
                rews.append(r)
                done = term or trunc
            stacked = {k: np.stack([o[k] for o in obs_list]) for k in OBS_SPEC}
            w.append(
                make_episode(
                    stacked,
                    np.asarray(acts, np.float32),
                    np.asarray(rews, np.float32),
                    terminal=bool(term),
                    metadata={"episode_id": i, "seed": seed},
                )
            )
    env.close()
    return Path(dest)
