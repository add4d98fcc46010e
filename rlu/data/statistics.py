"""Dataset statistics for agents that ask for them (``rlu.types.BatchSpec.statistics``),
computed once, vectorised, in bounded memory (columns are read in chunks of rows)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from rlu.types import ArraySpec, DataStatistics, RluError

CHUNK_ROWS = 1 << 16


def _mean_std(column: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-feature mean and (population) standard deviation of ``column[:n]``, in float64 over
    chunks of rows (Chan et al.'s pairwise update, so a chunked pass equals one pass)."""
    count: int = 0
    mean: Any = None
    m2: Any = None
    for start in range(0, n, CHUNK_ROWS):
        x = np.asarray(column[start : min(n, start + CHUNK_ROWS)], np.float64)
        c = len(x)
        mu = x.mean(axis=0)
        sq = ((x - mu) ** 2).sum(axis=0)
        if mean is None:
            count, mean, m2 = c, mu, sq
            continue
        delta = mu - mean
        total = count + c
        mean = mean + delta * (c / total)
        m2 = m2 + sq + delta**2 * (count * c / total)
        count = total
    if mean is None:
        raise RluError("the dataset has no steps; statistics need data")
    return mean.astype(np.float32), np.sqrt(m2 / count).astype(np.float32)


def dataset_statistics(ds: Any, names: Sequence[str]) -> DataStatistics:
    """The statistics ``names`` (``rlu.types.STATISTICS``) of dataset ``ds``."""
    out: dict[str, Any] = {}
    if "observation" in names:
        obs = ds.schema.observation
        if isinstance(obs, ArraySpec):
            if ds.schema.frame_stack > 1 or obs.dtype == "uint8":
                raise RluError(
                    f"{ds.path}: observation statistics are for feature observations; this "
                    "dataset holds images"
                )
            out["observation_mean"], out["observation_std"] = _mean_std(
                ds.column("observation"), ds.num_steps
            )
        else:
            means, stds = {}, {}
            for key, spec in obs.items():
                if spec.dtype == "uint8":
                    continue  # a camera: agents scale pixels themselves
                means[key], stds[key] = _mean_std(ds.column(f"observation/{key}"), ds.num_steps)
            out["observation_mean"], out["observation_std"] = means, stds
    if "reward" in names:
        r = np.asarray(ds.column("reward"), np.float64)
        last = np.asarray(ds.column("is_last"), bool)
        r = r[~last]  # an episode's last step holds no reward (RLDS)
        if not r.size:
            raise RluError(f"{ds.path}: no transitions; reward statistics need data")
        out.update(reward_mean=float(r.mean()), reward_std=float(r.std()),
                   reward_min=float(r.min()), reward_max=float(r.max()))  # fmt: skip
    if "return" in names:
        returns = ds.episode_returns()
        if not returns.size:
            raise RluError(
                f"{ds.path}: no whole episode (is_first to is_last), so no return range; this "
                "agent's return scaling (or dt's target rule) needs an episodes dataset (e.g. the "
                "release's episode family, or rlu generate), or for dt a target_return"
            )
        out.update(return_min=float(returns.min()), return_max=float(returns.max()))
    return DataStatistics(**out)
