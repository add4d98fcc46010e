"""The paper's evaluation protocols (§2.2, §5) over a table of finished runs, plus selection by
off-policy estimates.

A result record is a mapping with at least ``task``, ``agent``, ``config`` (a label of the
hyper-parameter setting), ``seed`` and ``score`` (the final evaluation score of that run:
raw return, or the normalised score for Atari).

- ``online_selection``: per (task, agent), the configuration with the best mean over seeds.
- ``offline_selection_naive``: per agent, the configuration with the best mean (median for
  Atari) over the domain's online-selection tasks, applied unchanged to its offline-selection
  tasks.
- ``select_by_estimate``: choose among candidates by an off-policy estimate computed from data
  only (``rlu.evaluation.fqe``); report Spearman rank correlation and regret@1 against the true
  returns.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from rlu.types import RluError


@dataclass(frozen=True)
class Selection:
    """The chosen configuration of one (task, agent) and its scores over seeds."""

    task: str
    agent: str
    config: str
    scores: tuple[float, ...]
    seeds: tuple[int, ...]

    @property
    def mean(self) -> float:
        """The mean score over seeds."""
        return float(np.mean(self.scores))

    @property
    def std(self) -> float | None:
        """The sample standard deviation (ddof 1) of the scores over seeds, as every spread rlu
        reports; None with one seed (it has no spread)."""
        return float(np.std(self.scores, ddof=1)) if len(self.scores) > 1 else None


def _group(records: Iterable[Mapping[str, Any]]) -> dict[tuple[str, str, str], dict[int, float]]:
    out: dict[tuple[str, str, str], dict[int, float]] = defaultdict(dict)
    for r in records:
        try:
            key = (str(r["task"]), str(r["agent"]), str(r["config"]))
            out[key][int(r["seed"])] = float(r["score"])
        except KeyError as e:
            raise RluError(
                f"result record {dict(r)!r} has no field {e.args[0]!r}; records need task, "
                "agent, config, seed and score"
            ) from None
    return out


def _selection(task: str, agent: str, config: str, by_seed: Mapping[int, float]) -> Selection:
    seeds = tuple(sorted(by_seed))
    return Selection(task, agent, config, tuple(by_seed[s] for s in seeds), seeds)


def online_selection(records: Iterable[Mapping[str, Any]]) -> dict[tuple[str, str], Selection]:
    """Best configuration per (task, agent) by mean score over seeds (ties: first label)."""
    best: dict[tuple[str, str], Selection] = {}
    for (task, agent, config), by_seed in sorted(_group(records).items()):
        sel = _selection(task, agent, config, by_seed)
        cur = best.get((task, agent))
        if cur is None or sel.mean > cur.mean:
            best[(task, agent)] = sel
    return best


def offline_selection_naive(
    records: Iterable[Mapping[str, Any]],
    online_tasks: Iterable[str],
    offline_tasks: Iterable[str],
    statistic: str = "mean",
) -> tuple[dict[str, str], dict[tuple[str, str], Selection]]:
    """Per agent, the configuration whose ``statistic`` (mean, or median for Atari) of per-task
    mean scores over ``online_tasks`` is best; returned with that configuration's results on
    ``offline_tasks``: ``({agent: config}, {(task, agent): Selection})``.

    A configuration must have results on every online task to be eligible.
    """
    if statistic not in ("mean", "median"):
        raise RluError(f"statistic={statistic!r}; use 'mean' or 'median'")
    agg = np.mean if statistic == "mean" else np.median
    online, offline = list(online_tasks), list(offline_tasks)
    groups = _group(records)
    per_agent: dict[str, dict[str, dict[str, float]]] = defaultdict(lambda: defaultdict(dict))
    for (task, agent, config), by_seed in groups.items():
        if task in online:
            per_agent[agent][config][task] = float(np.mean(list(by_seed.values())))
    chosen: dict[str, str] = {}
    for agent, configs in sorted(per_agent.items()):
        eligible = {c: t for c, t in configs.items() if all(x in t for x in online)}
        if not eligible:
            raise RluError(
                f"agent {agent!r}: no configuration has results on every online-selection task "
                f"({', '.join(online)}); finish those runs first"
            )
        scored = sorted((-float(agg([t[x] for x in online])), c) for c, t in eligible.items())
        chosen[agent] = scored[0][1]
    results = {}
    for task in offline:
        for agent, config in chosen.items():
            seeds = groups.get((task, agent, config))
            if seeds:
                results[(task, agent)] = _selection(task, agent, config, seeds)
    return chosen, results


# --- selection by off-policy estimates ------------------------------------------------------
def rankdata(x: Any) -> np.ndarray:
    """Ranks from 1, ties given their average rank (scipy.stats.rankdata's 'average')."""
    x = np.asarray(x, np.float64).reshape(-1)
    order = np.argsort(x, kind="mergesort")
    ranks = np.empty(x.size, np.float64)
    ranks[order] = np.arange(1, x.size + 1)
    _, inv, counts = np.unique(x, return_inverse=True, return_counts=True)
    sums = np.bincount(inv.reshape(-1), weights=ranks)
    return sums[inv.reshape(-1)] / counts[inv.reshape(-1)]


def spearman(a: Any, b: Any) -> float:
    """Spearman rank correlation (Pearson correlation of average ranks); NaN if either side is
    constant."""
    ra, rb = rankdata(a), rankdata(b)
    if ra.size != rb.size or ra.size < 2:
        raise RluError(f"spearman needs two vectors of equal length >= 2; got {ra.size}, {rb.size}")
    da, db = ra - ra.mean(), rb - rb.mean()
    denom = np.sqrt((da * da).sum() * (db * db).sum())
    return float((da * db).sum() / denom) if denom > 0 else float("nan")


@dataclass(frozen=True)
class EstimateSelection:
    """Offline selection by an estimate (FQE's): the candidate it chose, how its ranking correlates
    with the true returns, and the regret of the choice."""

    chosen: str
    """The candidate with the highest estimate."""
    spearman: float
    regret_at_1: float
    """True return of the best candidate minus that of the chosen one."""
    normalized_regret_at_1: float
    """regret@1 / (best true return - worst true return); 0 when every candidate ties."""


def select_by_estimate(
    estimates: Mapping[str, float], true_returns: Mapping[str, float]
) -> EstimateSelection:
    """Choose the candidate with the best estimate; score the choice against the true returns."""
    names = sorted(estimates)
    if sorted(true_returns) != names:
        raise RluError(
            "estimates and true returns name different candidates: "
            f"{sorted(set(names) ^ set(true_returns))}"
        )
    est = np.array([estimates[n] for n in names], np.float64)
    true = np.array([true_returns[n] for n in names], np.float64)
    chosen = int(np.argmax(est))
    regret = float(true.max() - true[chosen])
    spread = float(true.max() - true.min())
    return EstimateSelection(
        chosen=names[chosen],
        spearman=spearman(est, true) if len(names) > 1 else float("nan"),
        regret_at_1=regret,
        normalized_regret_at_1=regret / spread if spread > 0 else 0.0,
    )
