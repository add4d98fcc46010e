"""Evaluation: vectorised rollouts, scores and aggregates, the paper's protocols, FQE, reports.

Evaluation sees a policy callable and an env factory, never an agent or the training loop.
Imports numpy only; PyTorch (FQE) and matplotlib (reports) load when used.
"""

from __future__ import annotations

from rlu.evaluation.fqe import FQEConfig, fqe_estimate
from rlu.evaluation.protocols import (
    EstimateSelection,
    Selection,
    offline_selection_naive,
    online_selection,
    select_by_estimate,
    spearman,
)
from rlu.evaluation.rollout import EvalResult, evaluate, task_env_factory
from rlu.evaluation.scores import (
    aggregate_iqm,
    aggregate_mean,
    aggregate_median,
    best_behaviour_from_dataset,
    normalized_score,
    stratified_bootstrap_ci,
    task_bootstrap_interval,
)

__all__ = [
    "EstimateSelection",
    "EvalResult",
    "FQEConfig",
    "Selection",
    "aggregate_iqm",
    "aggregate_mean",
    "aggregate_median",
    "best_behaviour_from_dataset",
    "evaluate",
    "fqe_estimate",
    "normalized_score",
    "offline_selection_naive",
    "online_selection",
    "select_by_estimate",
    "spearman",
    "stratified_bootstrap_ci",
    "task_bootstrap_interval",
    "task_env_factory",
]
