"""The report's learning curves: evaluation return against learner steps, per task and agent.

Each run's evaluations come from its eval.jsonl (``rlu.training.runs.learning_curve``, given to the
report as each record's ``curve``). Per task and agent the curves are those of the configuration
the task's protocol chose (online policy selection on an online-selection task, naive offline
selection on an offline-selection one: the configuration of the tables), one line per seed and
their mean with a band of ± the sample standard deviation over seeds (ddof 1), at the steps
every seed evaluated (no band with one seed). Steps are learner steps as the run counted them:
an agent with a pre-training phase (BRAC's behaviour model) evaluates during it too, and the
report marks where that phase ends.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

NO_CURVES = (
    "no run's evaluations were found (each run's eval.jsonl, read from its folder: a sweep moved "
    "without its run folders has none)"
)
"""Why the panel is absent when ``curves`` finds none."""


def curves(
    records: Sequence[Mapping[str, Any]],
    tasks: Sequence[str],
    agents: Sequence[str],
    chosen: Mapping[tuple[str, str], tuple[str, str]],
) -> dict[str, Any] | None:
    """The ``curves`` panel (``numbers.PANELS``) from a domain's records, its tasks and agents
    in the report's order and, per (task, agent), the (configuration, protocol) its cells show;
    None when no run kept its evaluations (``NO_CURVES``)."""
    by_key = {(r["task"], r["agent"], r["config"], int(r["seed"])): r for r in records}
    panel = []
    without: list[str] = []
    for task in tasks:
        shown = {}
        for agent in agents:
            if (task, agent) not in chosen:
                continue
            config, protocol = chosen[(task, agent)]
            runs = sorted((k[3], r) for k, r in by_key.items() if k[:3] == (task, agent, config))
            seeds: list[dict[str, Any]] = [
                {
                    "seed": s,
                    "steps": [e["step"] for e in r["curve"]],
                    "means": [e["mean"] for e in r["curve"]],
                }
                for s, r in runs
                if r.get("curve")
            ]
            missing = [s for s, r in runs if not r.get("curve")]
            without += [f"{task} {agent} seed {s}" for s in missing]
            if not seeds:
                continue
            pretrain = {r.get("pretrain_steps") or 0 for _, r in runs}
            shown[agent] = {
                "config": config,
                "protocol": protocol,
                **mean_band([x["steps"] for x in seeds], [x["means"] for x in seeds]),
                "seeds": seeds,
                "pretrain_steps": max(pretrain),
            }
        if shown:
            panel.append({"task": task, "agents": shown})
    if not panel:
        return None
    return {"tasks": panel, "without_curve": without}


def mean_band(steps: Sequence[Sequence[int]], means: Sequence[Sequence[float]]) -> dict[str, Any]:
    """The mean over seeds at the steps every seed evaluated, and ± the sample std (ddof 1;
    None with one seed) there."""
    common = sorted(set.intersection(*(set(s) for s in steps))) if steps else []
    at = [dict(zip(s, m, strict=True)) for s, m in zip(steps, means, strict=True)]
    values = np.array([[row[x] for row in at] for x in common], np.float64).reshape(
        len(common), len(at)
    )
    mean = values.mean(axis=1) if common else np.zeros(0)
    std = values.std(axis=1, ddof=1) if len(at) > 1 and common else None
    return {
        "steps": common,
        "mean": mean.tolist(),
        "std": None if std is None else std.tolist(),
        "n_seeds": len(at),
    }
