"""rliable's aggregate views (Agarwal et al. 2021, "Deep RL at the edge of the statistical
precipice"): performance profiles and the probability of improvement, with 95 % stratified
bootstrap confidence intervals over seeds (tasks are the strata).

Per split under its own protocol (online policy selection on the online-selection tasks, naive
offline selection on the offline-selection ones), over the tasks every agent of the split has,
each agent's runs of its chosen configurations as a (seeds, tasks) matrix over the seeds every
one of those tasks has. Scores are the tables' (raw returns; Atari normalised).

- ``profiles``: the score distribution, the fraction of an agent's (seed, task) runs scoring
  above tau, at 101 values of tau spanning every score; its interval at each tau
  (``rliable.library.create_performance_profile``).
- ``improvement``: per pair of agents (X ranked above Y by IQM), P(X > Y): the probability that
  a run of X on a task, drawn at random, scores above one of Y (ties count one half: the
  Mann-Whitney U over nx ny), averaged over tasks, with its interval from a stratified
  independent bootstrap (``rliable.metrics.probability_of_improvement`` under
  ``rliable.library.get_interval_estimates``).

Both are rliable's numbers exactly: the same resamples in the same order from
``np.random.RandomState(seed)`` (rliable draws them from numpy's global generator, one
``choice(runs, (runs, tasks))`` per replicate and agent, X's then Y's for a pair) and the same
percentile rule; tests compare them with rliable's own. They are computed here, vectorised over
the replicates, because rliable computes each replicate in Python with a scipy call per task
and pair (bench/report_profiles.py measures both on the same scores).

With one seed per task the bootstrap has nothing to resample: the numbers stand without an
interval (``ci`` None), and the figures draw none.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from rlu.evaluation.scores import aggregate_iqm

TAUS = 101
"""Values of tau a profile is evaluated at."""
SIZE = 0.95
"""Coverage of every interval here."""


def _percentile(stats: np.ndarray, size: float = SIZE) -> np.ndarray:
    alpha = (1.0 - size) / 2
    return np.percentile(stats, [100 * alpha, 100 * (1 - alpha)], axis=0)


def score_distribution(scores: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """The fraction of (..., runs, tasks) scores above each tau: (..., len(taus))."""
    flat = scores.reshape(*scores.shape[:-2], -1)
    return (flat[..., None, :] > taus[:, None]).mean(axis=-1)


def performance_profile(
    scores: Mapping[str, np.ndarray],
    taus: np.ndarray,
    reps: int = 2000,
    size: float = SIZE,
    random_state: np.random.RandomState | int = 0,
    chunk: int = 250,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(profile, (2, len(taus)) interval) per agent of (runs, tasks) score matrices:
    ``rliable.library.create_performance_profile`` number for number."""
    rs = (
        random_state
        if isinstance(random_state, np.random.RandomState)
        else np.random.RandomState(random_state)
    )
    point, ci = {}, {}
    for name, x in scores.items():
        x = np.asarray(x, np.float64)
        runs, tasks = x.shape
        stats = np.empty((reps, len(taus)))
        cols = np.arange(tasks)
        for lo in range(0, reps, chunk):
            k = min(chunk, reps - lo)
            idx = rs.choice(runs, (k, runs, tasks), replace=True)
            stats[lo : lo + k] = score_distribution(x[idx, cols], taus)
        point[name] = score_distribution(x, taus)
        ci[name] = _percentile(stats, size)
    return point, ci


def _improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) of (..., nx, tasks) and (..., ny, tasks) scores, averaged over tasks."""
    gt = (x[..., :, None, :] > y[..., None, :, :]).sum(axis=(-3, -2))
    eq = (x[..., :, None, :] == y[..., None, :, :]).sum(axis=(-3, -2))
    return ((gt + 0.5 * eq) / (x.shape[-2] * y.shape[-2])).mean(axis=-1)


def probability_of_improvement(
    pairs: Mapping[str, tuple[np.ndarray, np.ndarray]],
    reps: int = 2000,
    size: float = SIZE,
    random_state: np.random.RandomState | int = 0,
) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """(P(X > Y), its (2,) interval) per pair of (runs, tasks) score matrices over the same
    tasks: ``rliable.library.get_interval_estimates(pairs,
    rliable.metrics.probability_of_improvement)`` number for number."""
    rs = (
        random_state
        if isinstance(random_state, np.random.RandomState)
        else np.random.RandomState(random_state)
    )
    point, ci = {}, {}
    for name, (x, y) in pairs.items():
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        cols = np.arange(x.shape[1])
        ix = np.empty((reps, *x.shape), np.int64)
        iy = np.empty((reps, *y.shape), np.int64)
        for r in range(reps):  # rliable's order: X's resample, then Y's, per replicate
            ix[r] = rs.choice(x.shape[0], x.shape, replace=True)
            iy[r] = rs.choice(y.shape[0], y.shape, replace=True)
        stats = np.concatenate(
            [
                _improvement(x[ix[lo : lo + 200], cols], y[iy[lo : lo + 200], cols])
                for lo in range(0, reps, 200)
            ]
        )
        point[name] = float(_improvement(x, y))
        ci[name] = _percentile(stats, size)
    return point, ci


def matrices(
    splits: Mapping[str, Mapping[tuple[str, str], Any]],
    split_tasks: Mapping[str, Sequence[str]],
    agents: Sequence[str],
) -> dict[str, dict[str, Any]]:
    """Per split, the tasks every agent of it has and each agent's (seeds, tasks) scores over
    the seeds all those tasks have (``splits``: per split, the selections by (task, agent))."""
    out: dict[str, dict[str, Any]] = {}
    for split, sel in splits.items():
        names = [a for a in agents if any((t, a) in sel for t in split_tasks[split])]
        tasks = [t for t in split_tasks[split] if all((t, a) in sel for a in names)]
        if not names or not tasks:
            continue
        scores, seeds, configs = {}, {}, {}
        for a in names:
            cells = [sel[(t, a)] for t in tasks]
            common = sorted(set.intersection(*(set(c.seeds) for c in cells)))
            if not common:
                continue
            by_seed = [dict(zip(c.seeds, c.scores, strict=True)) for c in cells]
            scores[a] = np.array([[b[s] for b in by_seed] for s in common], np.float64)
            seeds[a] = common
            configs[a] = {t: c.config for t, c in zip(tasks, cells, strict=True)}
        if scores:
            out[split] = {"tasks": tasks, "scores": scores, "seeds": seeds, "configs": configs}
    return out


def profiles(mats: Mapping[str, Mapping[str, Any]], reps: int) -> dict[str, Any]:
    """The ``profiles`` panel: per split, tau and each agent's profile with its interval."""
    out: dict[str, Any] = {}
    for split, m in mats.items():
        every = np.concatenate([x.ravel() for x in m["scores"].values()])
        lo, hi = float(every.min()), float(every.max())
        taus = np.linspace(min(lo, 0.0), hi if hi > lo else lo + 1.0, TAUS)
        point, ci = performance_profile(m["scores"], taus, reps=reps)
        agents = {}
        for a, x in m["scores"].items():
            one = x.shape[0] < 2
            agents[a] = {
                "fraction": [float(v) for v in point[a]],
                "ci": None if one else [[float(v) for v in row] for row in ci[a]],
                "seeds": m["seeds"][a],
                "configs": m["configs"][a],
            }
        out[split] = {"tasks": m["tasks"], "tau": taus.tolist(), "agents": agents}
    return out


def improvement(mats: Mapping[str, Mapping[str, Any]], reps: int) -> dict[str, Any]:
    """The ``improvement`` panel: per split, P(X > Y) with its interval for every pair of
    agents, X ranked above Y by the IQM of its runs."""
    out: dict[str, Any] = {}
    for split, m in mats.items():
        scores = m["scores"]
        if len(scores) < 2:
            continue
        iqm = {a: float(aggregate_iqm(x)) for a, x in scores.items()}
        ranked = sorted(scores, key=lambda a: (-iqm[a], a))
        pairs = [(x, y) for i, x in enumerate(ranked) for y in ranked[i + 1 :]]
        point, ci = probability_of_improvement(
            {f"{x},{y}": (scores[x], scores[y]) for x, y in pairs}, reps=reps
        )
        rows = []
        for x, y in pairs:
            key = f"{x},{y}"
            one = scores[x].shape[0] < 2 and scores[y].shape[0] < 2
            rows.append(
                {
                    "x": x,
                    "y": y,
                    "probability": point[key],
                    "ci": None if one else [float(v) for v in ci[key]],
                    "seeds": [len(m["seeds"][x]), len(m["seeds"][y])],
                }
            )
        out[split] = {"tasks": m["tasks"], "iqm": iqm, "pairs": rows}
    return out
