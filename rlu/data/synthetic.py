"""Synthetic episodes in a task's exact schema (random values): for the round-trip demo, the
benches and the tests. Never presented as real data: the manifest's provenance says synthetic."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.store import DatasetWriter, Schema
from rlu.segments import Segment, make_episode
from rlu.types import ArraySpec, DiscreteSpec


def _random(spec: ArraySpec, n: int, rng: np.random.Generator) -> np.ndarray:
    if np.dtype(spec.dtype) == np.uint8:
        return rng.integers(0, 256, size=(n, *spec.shape), dtype=np.uint8)
    return rng.standard_normal((n, *spec.shape), dtype=np.float32).astype(spec.dtype)


def random_episodes(
    schema: Schema,
    num_episodes: int,
    episode_length: int,
    seed: int = 0,
    terminal_prob: float = 0.5,
    vary_length: bool = False,
) -> Iterator[Segment]:
    """``num_episodes`` episodes of ``episode_length`` steps (fewer if ``vary_length``)."""
    rng = np.random.default_rng(seed)
    for i in range(num_episodes):
        n = int(rng.integers(1, episode_length + 1)) if vary_length else episode_length
        if isinstance(schema.observation, ArraySpec):
            obs: Any = _random(schema.observation, n + 1, rng)
        else:
            obs = {k: _random(s, n + 1, rng) for k, s in schema.observation.items()}
        if isinstance(schema.action, DiscreteSpec):
            actions = rng.integers(0, schema.action.num_values, size=n).astype(schema.action.dtype)
        else:
            lo, hi = schema.action.minimum, schema.action.maximum
            actions = rng.uniform(lo, hi, (n, *schema.action.shape)).astype(schema.action.dtype)
        rewards = rng.random(n, dtype=np.float32)
        yield make_episode(
            obs,
            actions,
            rewards,
            terminal=bool(rng.random() < terminal_prob),
            metadata={"episode_id": i, "seed": seed},
        )


def write_synthetic(
    dest: str | Path,
    schema: Schema,
    num_episodes: int,
    episode_length: int,
    seed: int = 0,
    **kwargs: Any,
) -> Path:
    prov = {
        "source": "synthetic",
        "generator": "rlu.data.synthetic.random_episodes",
        "seed": seed,
        "episodes": num_episodes,
        "episode_length": episode_length,
    }
    with DatasetWriter(dest, schema, prov) as w:
        for seg in random_episodes(schema, num_episodes, episode_length, seed, **kwargs):
            w.append(seg)
    return Path(dest)
