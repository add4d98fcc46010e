"""Scores and aggregates (paper §5 and appendix; Agarwal et al. 2021 for IQM).

- Control suite, locomotion, RWRL: raw episode returns.
- Atari: ``100 * (score - random) / (best_behaviour - random)`` on raw game scores, where
  ``best_behaviour`` is the best snapshot of the data-generating DQN (paper appendix "Atari
  Results Normalization"). Random and best-behaviour scores are inputs: ``load_reference_scores``
  reads ``rlu/resources/random_scores.json`` and ``atari_best_behaviour.json`` (its numbers and
  their provenance: ``rlu.evaluation.reference``); ``best_behaviour_from_dataset`` recomputes the
  latter from a converted ``atari_episodes_ordered`` dataset.
- Aggregates over tasks: the mean (the median for Atari) with a bootstrapped [25, 75] percentile
  interval over tasks, as in the paper's Atari figures; the interquartile mean (IQM) with
  stratified bootstrap confidence intervals over runs, as rliable computes them.

Every function is array in, array out; bootstraps draw all resamples at once from an explicit
generator. ``stratified_bootstrap_ci`` reproduces ``rliable.library.get_interval_estimates``
number for number when given ``np.random.RandomState(seed)`` and rliable runs after
``np.random.seed(seed)`` (rliable draws its indices from numpy's global generator).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from importlib import resources
from typing import Any

import numpy as np

from rlu.files import read_json
from rlu.types import FormatError, RluError

AggregateFn = Callable[[np.ndarray], np.ndarray]


# --- normalisation --------------------------------------------------------------------------
def normalized_score(score: Any, random_score: float, best_behaviour: float) -> np.ndarray:
    """``100 * (score - random) / (best_behaviour - random)`` (paper appendix, Atari)."""
    denom = float(best_behaviour) - float(random_score)
    if denom == 0.0:
        raise RluError(
            f"best_behaviour score equals the random score ({random_score}); the normalisation "
            "is undefined: check the reference scores for this game"
        )
    return 100.0 * (np.asarray(score, np.float64) - float(random_score)) / denom


def normalize_scores(
    scores: Mapping[str, Any],
    random_scores: Mapping[str, float],
    best_behaviour: Mapping[str, float],
) -> dict[str, np.ndarray]:
    """Normalise ``{game: score(s)}``; a game missing from either reference is an error."""
    out = {}
    for game, s in scores.items():
        missing = [
            n
            for n, ref in (("random", random_scores), ("best_behaviour", best_behaviour))
            if game not in ref
        ]
        if missing:
            raise RluError(
                f"no {' or '.join(missing)} score for game {game!r}; add it to the reference "
                "scores (rlu/resources/*.json) or pass it explicitly"
            )
        out[game] = normalized_score(s, random_scores[game], best_behaviour[game])
    return out


def best_behaviour_from_dataset(ds: Any) -> float:
    """The best snapshot of the data-generating runs in a converted ``atari_episodes_ordered``
    dataset: per run, the checkpoint with the highest mean raw episode return, averaged over
    the runs (``rlu.evaluation.reference``, the rule ``rlu envs best-behaviour`` applies to
    release files).

    Needs each episode's raw ``episode_return`` and its ``checkpoint``: converted Atari
    transition files have neither (their returns are clipped, their episodes unordered)."""
    from rlu.evaluation.reference import best_of_runs

    returns = np.asarray(ds.metadata("episode_return"), np.float64)
    run = np.asarray(ds.metadata("run"), np.int64)
    ckpt = np.asarray(ds.metadata("checkpoint"), np.int64)
    ok = ~np.isnan(returns) & (ckpt >= 0)
    if not ok.any():
        raise RluError(
            f"{ds.path}: no episode has both a raw episode_return and a checkpoint (segment "
            "metadata); the best snapshot is computed from atari_episodes_ordered data, or use "
            "the shipped rlu/resources/atari_best_behaviour.json"
        )
    per_run: dict[int, dict[int, list[float]]] = {}
    for r, c, x in zip(run[ok].tolist(), ckpt[ok].tolist(), returns[ok].tolist(), strict=True):
        per_run.setdefault(r, {}).setdefault(c, []).append(x)
    return float(best_of_runs(per_run)["mean"])


def load_reference_scores(name: str) -> dict[str, float]:
    """``{task or game: score}`` from ``rlu/resources/<name>.json`` or from a ``.json`` path.

    The file's ``scores`` field (or the whole file) maps keys to a number or to a record with a
    ``mean`` (the format of ``random_scores.json``)."""

    if name.endswith(".json"):  # a file of the user's: bounded, a regular file, JSON
        data = read_json(name, fix="check the path, or pass a file rlu envs random-scores or "
                         "rlu envs best-behaviour wrote")  # fmt: skip
    else:
        try:
            text = resources.files("rlu.resources").joinpath(f"{name}.json").read_text()
        except FileNotFoundError:
            raise RluError(
                f"rlu/resources/{name}.json is missing; pass the scores explicitly or install "
                "the part of rlu that provides it"
            ) from None
        data = json.loads(text)
    if not isinstance(data, Mapping):
        raise FormatError(f"reference scores {name}: not a JSON object of scores")
    scores = data.get("scores", data)
    out = {}
    for k, v in scores.items():
        if isinstance(v, Mapping) and isinstance(v.get("mean"), int | float):
            out[k] = float(v["mean"])
        elif isinstance(v, int | float) and not isinstance(v, bool):
            out[k] = float(v)
    return out


# --- aggregates over (runs, tasks) ----------------------------------------------------------
def aggregate_mean(scores: np.ndarray) -> np.ndarray:
    """Mean over tasks of the per-task mean over runs; ``scores`` is (..., runs, tasks)."""
    return np.asarray(scores, np.float64).mean(axis=-2).mean(axis=-1)


def aggregate_median(scores: np.ndarray) -> np.ndarray:
    """Median over tasks of the per-task mean over runs (the paper's Atari aggregate)."""
    return np.median(np.asarray(scores, np.float64).mean(axis=-2), axis=-1)


def aggregate_iqm(scores: np.ndarray) -> np.ndarray:
    """Interquartile mean of all (run, task) scores: the 25 %-trimmed mean, cutting
    ``floor(0.25 n)`` values from each end (scipy.stats.trim_mean's rule)."""
    x = np.asarray(scores, np.float64)
    flat = np.sort(x.reshape(*x.shape[:-2], -1), axis=-1)
    n = flat.shape[-1]
    cut = int(0.25 * n)
    return flat[..., cut : n - cut].mean(axis=-1)


AGGREGATES: dict[str, AggregateFn] = {
    "mean": aggregate_mean,
    "median": aggregate_median,
    "iqm": aggregate_iqm,
}


def _as_runs_tasks(scores: Any) -> np.ndarray:
    x = np.asarray(scores, np.float64)
    if x.ndim != 2 or 0 in x.shape:
        raise RluError(f"scores must be a non-empty (runs, tasks) matrix; got shape {x.shape}")
    if not np.isfinite(x).all():
        raise RluError("scores contain NaN or inf; every (run, task) needs a finite score")
    return x


def stratified_bootstrap_ci(
    scores: Any,
    aggregate: str | AggregateFn = "iqm",
    reps: int = 50_000,
    size: float = 0.95,
    random_state: np.random.RandomState | int | None = 0,
    chunk: int = 2_000,
) -> tuple[float, tuple[float, float]]:
    """Point estimate and percentile confidence interval of ``aggregate`` by stratified
    bootstrap: each task's runs are resampled with replacement (tasks are the strata).

    ``scores`` is (runs, tasks). Same resamples, order and percentile rule as rliable.
    """
    x = _as_runs_tasks(scores)
    fn = AGGREGATES[aggregate] if isinstance(aggregate, str) else aggregate
    rs = (
        random_state
        if isinstance(random_state, np.random.RandomState)
        else np.random.RandomState(random_state)
    )
    runs, tasks = x.shape
    stats = np.empty(reps, np.float64)
    cols = np.arange(tasks)
    for lo in range(0, reps, chunk):
        k = min(chunk, reps - lo)
        # one (runs, tasks) index draw per replicate, in replicate order (rliable's stream)
        idx = rs.choice(runs, (k, runs, tasks), replace=True)
        stats[lo : lo + k] = fn(x[idx, cols])
    alpha = (1.0 - size) / 2
    low, high = np.percentile(stats, [100 * alpha, 100 * (1 - alpha)])
    return float(fn(x)), (float(low), float(high))


def task_bootstrap_interval(
    task_scores: Any,
    statistic: str = "mean",
    reps: int = 10_000,
    percentiles: tuple[float, float] = (25.0, 75.0),
    seed: int = 0,
) -> tuple[float, tuple[float, float]]:
    """The paper's aggregate over tasks with a bootstrapped percentile interval: ``statistic``
    (mean, or median for Atari) of per-task scores, tasks resampled with replacement."""
    x = np.asarray(task_scores, np.float64).reshape(-1)
    if x.size == 0 or not np.isfinite(x).all():
        raise RluError("task scores must be a non-empty vector of finite numbers")
    if statistic not in ("mean", "median"):
        raise RluError(f"statistic={statistic!r}; use 'mean' or 'median'")
    fn = np.mean if statistic == "mean" else np.median
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, x.size, size=(reps, x.size))
    stats = fn(x[idx], axis=1)
    low, high = np.percentile(stats, percentiles)
    return float(fn(x)), (float(low), float(high))


def domain_statistic(domain: str) -> str:
    """The paper's aggregate over a domain's tasks: median for Atari, mean elsewhere."""
    from rlu.domains import DOMAINS

    known = DOMAINS.get(domain)  # a report may name a domain of its own: the mean
    return known.statistic if known is not None else "mean"
