"""The numbers of ``rlu report``: a sweep's result records in, one JSON-serialisable dict out.

Pure: no files written, nothing drawn (``rlu.evaluation.report.render`` turns this dict into
Markdown, HTML and PNG). Per domain, the report holds the domain's ``agents`` and ``tasks`` and
one entry per *panel*:

- ``online``: task x agent, mean ± std over seeds of the final evaluation score of the
  configuration chosen by online policy selection (best per task), ``bold`` on the best mean of a
  row and on every mean ± std that overlaps it (the paper's convention), with the paper's number
  beside ours where the task and agent match (``rlu/resources/paper_results.json``, a copy of the
  appendix tables of Gulcehre et al. 2020);
- ``offline_naive``: when a domain's sweep holds both online- and offline-selection tasks, the
  naive offline policy selection (the configuration with the best mean, median for Atari, over
  the online tasks, applied unchanged to the offline ones);
- ``aggregates``: per agent, the mean (median for Atari, on normalised scores) over tasks with a
  bootstrapped [25, 75] percentile interval, and the IQM with a 95 % stratified bootstrap
  confidence interval over seeds (Agarwal et al. 2021, rliable);
- ``fqe``: offline policy selection by FQE estimates, when ``fqe.json`` is given;
- ``dataset_p90``: each task's dataset 90th-percentile episode return, when datasets are named.

Adding a panel is one function here, ``panel(ctx: DomainContext) -> dict | None`` registered in
``PANELS`` (None: the panel does not apply to this domain), plus one renderer registered under
the same name in ``rlu.evaluation.report.render.RENDERERS``.

Task metadata (domain, selection split) comes from ``rlu.tasks``; a task id that is not in the
registry is reported under the domain ``other`` as an online-selection task.
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from typing import Any

import numpy as np

from rlu.evaluation.protocols import Selection, offline_selection_naive, online_selection
from rlu.evaluation.scores import (
    domain_statistic,
    load_reference_scores,
    normalized_score,
    stratified_bootstrap_ci,
    task_bootstrap_interval,
)
from rlu.types import RluError

# the paper's spelling of task names that differ from ours beyond case and spaces
_PAPER_ALIASES = {"rodenttwotouch": "rodenttwotap"}


def _key(name: str) -> str:
    k = name.lower().replace(" ", "").replace("_", "")
    return _PAPER_ALIASES.get(k, k)


def task_info(task_id: str) -> tuple[str, str, str]:
    """(domain, selection, display name) of a task id."""
    from rlu.tasks import get_task

    try:
        t = get_task(task_id)
    except RluError:
        return "other", "online", task_id
    if t.id != task_id:  # a bare name that get_task resolved; report it under its own id
        return "other", "online", task_id
    return t.domain, t.selection, t.name


def load_paper_results() -> dict[str, Any]:
    return json.loads(resources.files("rlu.resources").joinpath("paper_results.json").read_text())


def paper_entry(
    task_id: str, agent: str, paper: Mapping[str, Any] | None = None
) -> dict[str, Any] | None:
    """The paper's ``{mean, std, bold}`` for a task and agent, or None where the paper has none."""
    paper = load_paper_results() if paper is None else paper
    domain, _, name = task_info(task_id)
    table = paper.get(domain)
    if not isinstance(table, Mapping):
        return None
    rows = {_key(k): v for k, v in table.items()}
    row = rows.get(_key(name))
    if row is None:
        return None
    cols = {k.lower(): v for k, v in row.items()}
    return cols.get(agent.split(".")[-1].lower())


def dataset_percentile(dataset: str, q: float = 90.0) -> float | None:
    """The ``q``-th percentile of a dataset's episode returns (None if it has no whole episode)."""
    from rlu.data import open_dataset

    returns = open_dataset(dataset).episode_returns()
    return float(np.percentile(returns, q)) if len(returns) else None


# --- the numbers ----------------------------------------------------------------------------
@dataclass(frozen=True)
class DomainContext:
    """Everything a panel may read about one domain of a sweep."""

    domain: str
    records: tuple[Mapping[str, Any], ...]
    """The sweep's records of this domain, raw scores."""
    scored: tuple[Mapping[str, Any], ...]
    """The same records with scores normalised where the domain normalises (Atari)."""
    agents: tuple[str, ...]
    tasks: tuple[str, ...]
    online_tasks: tuple[str, ...]
    offline_tasks: tuple[str, ...]
    normalised: bool
    paper: Mapping[str, Any]
    datasets: Mapping[str, str]
    fqe: Mapping[str, Any] | None
    reps: int


def online_panel(ctx: DomainContext) -> dict[str, Any]:
    return _table(online_selection(ctx.records), ctx.tasks, ctx.agents, ctx.paper)


def offline_naive_panel(ctx: DomainContext) -> dict[str, Any] | None:
    if not (ctx.online_tasks and ctx.offline_tasks):
        return None
    stat = domain_statistic(ctx.domain)
    chosen, _ = offline_selection_naive(
        list(ctx.scored), list(ctx.online_tasks), list(ctx.offline_tasks), stat
    )
    picked = [
        r
        for r in ctx.records
        if r["task"] in ctx.offline_tasks and r["config"] == chosen[r["agent"]]
    ]
    return {
        "chosen": chosen,
        **_table(online_selection(picked), ctx.offline_tasks, ctx.agents, ctx.paper),
    }


def aggregates_panel(ctx: DomainContext) -> dict[str, Any] | None:
    if ctx.domain == "atari" and not ctx.normalised:
        return None  # Atari aggregates are over normalised scores only
    return _aggregates(online_selection(ctx.scored), ctx.tasks, ctx.agents, ctx.domain, ctx.reps)


def fqe_panel(ctx: DomainContext) -> list[dict[str, Any]] | None:
    if not ctx.fqe:
        return None
    return [x for x in ctx.fqe.get("selections", []) if x["task"] in ctx.tasks]


def dataset_p90_panel(ctx: DomainContext) -> dict[str, float | None] | None:
    if not ctx.datasets:
        return None
    return {t: dataset_percentile(ctx.datasets[t]) for t in ctx.tasks if t in ctx.datasets}


Panel = Callable[[DomainContext], Any]
PANELS: dict[str, Panel] = {
    "online": online_panel,
    "offline_naive": offline_naive_panel,
    "aggregates": aggregates_panel,
    "fqe": fqe_panel,
    "dataset_p90": dataset_p90_panel,
}
"""Every panel of a domain, in report order (``rlu.evaluation.report.render`` renders them)."""


def build_report(
    records: Sequence[Mapping[str, Any]],
    datasets: Mapping[str, str] | None = None,
    random_scores: Mapping[str, float] | None = None,
    best_behaviour: Mapping[str, float] | None = None,
    reps: int = 2000,
    fqe: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Every number of the report (JSON-serialisable), from a sweep's result records (and, if
    given, the FQE selections that ``rlu.train.fqe_selection`` wrote)."""
    paper = load_paper_results()
    by_domain: dict[str, list[Mapping[str, Any]]] = defaultdict(list)
    for r in records:
        if r.get("score") is None:
            raise RluError(f"run {r.get('run')} has no evaluation score; rerun it with evaluation")
        by_domain[task_info(r["task"])[0]].append(r)
    out: dict[str, Any] = {"domains": {}}
    for domain, recs in sorted(by_domain.items()):
        agents = sorted({r["agent"] for r in recs})
        tasks = sorted({r["task"] for r in recs}, key=lambda t: (task_info(t)[1] != "online", t))
        norm = None
        if domain == "atari":
            norm, refs = _atari_normaliser(tasks, random_scores, best_behaviour)
        # tables show raw returns (as the paper's appendix does); selection across tasks and
        # the aggregates use normalised scores for Atari
        scored = [
            {**r, "score": float(norm(r["task"], r["score"])) if norm else float(r["score"])}
            for r in recs
        ]
        ctx = DomainContext(
            domain=domain,
            records=tuple(recs),
            scored=tuple(scored),
            agents=tuple(agents),
            tasks=tuple(tasks),
            online_tasks=tuple(t for t in tasks if task_info(t)[1] == "online"),
            offline_tasks=tuple(t for t in tasks if task_info(t)[1] == "offline"),
            normalised=norm is not None,
            paper=paper,
            datasets=dict(datasets or {}),
            fqe=fqe,
            reps=reps,
        )
        dom: dict[str, Any] = {"agents": agents, "tasks": tasks, "normalised": norm is not None}
        if norm is not None:
            dom["reference_scores"] = refs
        dom["panels"] = []
        for name, panel in PANELS.items():
            data = panel(ctx)
            if data is not None:
                dom[name] = data
                dom["panels"].append(name)
        out["domains"][domain] = dom
    return out


def _atari_normaliser(tasks, random_scores, best_behaviour):
    """(score normaliser, the reference scores used) or (None, None) where a game lacks one.

    The references are the given ones or the shipped files (``rlu/resources``); a game without
    both leaves the domain unnormalised (there is no estimate from the sweep's data: a
    transition dataset's returns are clipped and span a whole run, not one snapshot)."""
    if random_scores is None:
        try:
            random_scores = load_reference_scores("random_scores")
        except RluError:
            random_scores = {}
    if best_behaviour is None:
        best_behaviour = load_reference_scores("atari_best_behaviour")

    def ref(table: Mapping[str, float], task: str) -> float | None:
        # reference files key by task id (random_scores.json) or by game name
        for key in (task, task_info(task)[2]):
            if key in table:
                return table[key]
        return None

    refs: dict[str, Any] = {}
    for t in tasks:
        rnd, best, source = ref(random_scores, t), ref(best_behaviour, t), "given"
        if rnd is None or best is None:
            return None, None
        refs[t] = {"random": rnd, "best_behaviour": best, "best_behaviour_source": source}

    def norm(task: str, score: float) -> float:
        r = refs[task]
        return float(normalized_score(score, r["random"], r["best_behaviour"]))

    return norm, refs


def _table(
    sel: Mapping[tuple[str, str], Selection],
    tasks: Sequence[str],
    agents: Sequence[str],
    paper: Mapping[str, Any] | None,
) -> dict[str, Any]:
    rows = []
    for task in tasks:
        cells = {}
        for agent in agents:
            s = sel.get((task, agent))
            if s is None:
                continue
            cell = {
                "config": s.config,
                "mean": s.mean,
                "std": s.std,
                "seeds": list(s.seeds),
                "scores": list(s.scores),
            }
            if paper is not None:
                cell["paper"] = paper_entry(task, agent, paper)
            cells[agent] = cell
        # the paper's bold: the best mean, and every cell whose mean ± std overlaps the best's
        best = max(cells.values(), key=lambda c: c["mean"], default=None)
        for c in cells.values():
            c["bold"] = c["mean"] + c["std"] >= best["mean"] - best["std"]
        rows.append({"task": task, "cells": cells})
    return {"rows": rows}


def _aggregates(sel, tasks, agents, domain, reps) -> dict[str, Any]:
    stat = domain_statistic(domain)
    out = {"statistic": stat}
    for agent in agents:
        cells = [sel[(t, agent)] for t in tasks if (t, agent) in sel]
        if not cells:
            continue
        task_means = [c.mean for c in cells]
        est, (lo, hi) = task_bootstrap_interval(task_means, stat, reps=reps)
        entry: dict[str, Any] = {"tasks": len(cells), stat: est, "interval_25_75": [lo, hi]}
        common = sorted(set.intersection(*(set(c.seeds) for c in cells)))
        if common:
            matrix = np.array(
                [[dict(zip(c.seeds, c.scores, strict=True))[s] for c in cells] for s in common]
            )
            iqm, (ilo, ihi) = stratified_bootstrap_ci(matrix, "iqm", reps=reps)
            entry.update({"iqm": iqm, "iqm_ci95": [ilo, ihi]})
        out[agent] = entry
    return out
