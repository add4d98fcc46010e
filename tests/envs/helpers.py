"""Shared checks for the env tests."""

from __future__ import annotations

import warnings

import numpy as np


def rollout(env, seed: int, steps: int, action_seed: int = 0) -> list:
    """Observations of `steps` steps under seeded random actions, resetting at episode ends."""
    rng = np.random.default_rng(action_seed)
    space = env.action_space
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for _ in range(steps):
        if hasattr(space, "n"):
            a = int(rng.integers(space.n))
        else:
            a = rng.uniform(-1, 1, space.shape).astype(np.float32)
        obs, _, term, trunc, _ = env.step(a)
        out.append(obs)
        if term or trunc:
            obs, _ = env.reset()
            out.append(obs)
    return out


def same(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    return np.array_equal(a, b)


def check_env_quietly(env) -> None:
    """gymnasium's checker; its warnings about unbounded feature Boxes are expected."""
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(env, skip_render_check=True)
