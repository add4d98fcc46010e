"""``rlu report SWEEP_DIR``: the paper's tables and figures from a sweep's results, as Markdown,
HTML, PNG and JSON (the numbers the tables print).

- Tables (per domain): task x agent, mean ± std over seeds of the final evaluation score of the
  configuration chosen by online policy selection (best per task), in bold the best mean of a
  row and every mean ± std that overlaps it (the paper's convention), with the paper's number
  beside ours where the task and agent match
  (``rlu/resources/paper_results.json``, a copy of the paper's appendix tables). When a domain's
  sweep holds both online- and offline-selection tasks, a second table gives the naive offline
  policy selection (the configuration with the best mean, median for Atari, over the online
  tasks, applied unchanged to the offline ones).
- Aggregates (per domain and agent): the mean (median for Atari, on normalised scores) over tasks
  with a bootstrapped [25, 75] percentile interval, and the IQM with a 95 % stratified bootstrap
  confidence interval over seeds.
- Figures: per-task bars (agents, ± std) with the dataset's 90th-percentile episode return as a
  line; for Atari, median normalised score bars with their [25, 75] intervals.

Task metadata (domain, selection split) comes from ``rlu.tasks``; a task id that is not in the
registry is reported under the domain ``other`` as an online-selection task. matplotlib is
imported when the PNGs are drawn (the ``report`` extra).
"""

from __future__ import annotations

import html
import json
import os
from collections import defaultdict
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path
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


def _fmt(mean: float, std: float) -> str:
    return f"{mean:.1f} ± {std:.1f}"


def dataset_percentile(dataset: str, q: float = 90.0) -> float | None:
    """The ``q``-th percentile of a dataset's episode returns (None if it has no whole episode)."""
    from rlu.data import open_dataset

    returns = open_dataset(dataset).episode_returns()
    return float(np.percentile(returns, q)) if len(returns) else None


# --- the numbers ----------------------------------------------------------------------------
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
        online = [t for t in tasks if task_info(t)[1] == "online"]
        offline = [t for t in tasks if task_info(t)[1] == "offline"]
        norm = None
        if domain == "atari":
            norm, refs = _atari_normaliser(tasks, random_scores, best_behaviour)
        scored = [
            {**r, "score": float(norm(r["task"], r["score"])) if norm else float(r["score"])}
            for r in recs
        ]
        dom: dict[str, Any] = {"agents": agents, "tasks": tasks, "normalised": norm is not None}
        if norm is not None:
            dom["reference_scores"] = refs
        # tables show raw returns (as the paper's appendix does); selection across tasks and
        # the aggregates use normalised scores for Atari
        dom["online"] = _table(online_selection(recs), tasks, agents, paper)
        if online and offline:
            stat = domain_statistic(domain)
            chosen, _ = offline_selection_naive(scored, online, offline, stat)
            picked = [r for r in recs if r["task"] in offline and r["config"] == chosen[r["agent"]]]
            dom["offline_naive"] = {
                "chosen": chosen,
                **_table(online_selection(picked), offline, agents, paper),
            }
        if domain != "atari" or norm is not None:
            dom["aggregates"] = _aggregates(online_selection(scored), tasks, agents, domain, reps)
        if fqe:
            dom["fqe"] = [x for x in fqe.get("selections", []) if x["task"] in tasks]
        if datasets:
            dom["dataset_p90"] = {
                t: dataset_percentile(datasets[t]) for t in tasks if t in datasets
            }
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


# --- writing --------------------------------------------------------------------------------
def _md_table(table: Mapping[str, Any], agents: Sequence[str], with_paper: bool) -> list[str]:
    head = ["task"]
    for a in agents:
        head.append(a)
        if with_paper:
            head.append(f"{a} (paper)")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in table["rows"]:
        vals = [row["task"]]
        for a in agents:
            c = row["cells"].get(a)
            text = "" if c is None else _fmt(c["mean"], c["std"])
            vals.append(f"**{text}**" if c and c["bold"] else text)
            if with_paper:
                p = c.get("paper") if c else None
                vals.append("" if not p else _fmt(p["mean"], p["std"]))
        lines.append("| " + " | ".join(vals) + " |")
    return lines


def _markdown(rep: Mapping[str, Any], figures: Mapping[str, list[str]]) -> str:
    lines = ["# rlu report", ""]
    for domain, dom in rep["domains"].items():
        agents = dom["agents"]
        unit = "episode return"
        with_paper = any(
            c.get("paper") for row in dom["online"]["rows"] for c in row["cells"].values()
        )
        lines += [
            f"## {domain}",
            "",
            f"Online policy selection: {unit}, mean ± std over seeds of the best "
            "configuration per task; in bold the best and those whose mean ± std overlaps it."
            + (" The paper's numbers (raw returns) are beside ours." if with_paper else ""),
            "",
        ]
        lines += _md_table(dom["online"], agents, with_paper) + [""]
        if "offline_naive" in dom:
            chosen = ", ".join(f"{a}: {c}" for a, c in dom["offline_naive"]["chosen"].items())
            lines += [
                "Offline policy selection (naive): configuration chosen on the online "
                f"tasks ({chosen}).",
                "",
            ]
            lines += _md_table(dom["offline_naive"], agents, with_paper) + [""]
        if "aggregates" in dom:
            agg = dom["aggregates"]
            stat = agg["statistic"]
            what = "normalised scores (%)" if dom["normalised"] else "returns"
            lines += [
                f"Aggregate of {what} over tasks: {stat} with bootstrapped [25, 75] "
                "interval; IQM with "
                "95 % stratified bootstrap CI over seeds.",
                "",
                f"| agent | tasks | {stat} | [25, 75] | IQM | IQM 95 % CI |",
                "|---|---|---|---|---|---|",
            ]
            for a in agents:
                e = agg.get(a)
                if not e:
                    continue
                lo, hi = e["interval_25_75"]
                iqm = f"{e['iqm']:.1f}" if "iqm" in e else ""
                ci = f"[{e['iqm_ci95'][0]:.1f}, {e['iqm_ci95'][1]:.1f}]" if "iqm" in e else ""
                lines.append(
                    f"| {a} | {e['tasks']} | {e[stat]:.1f} | [{lo:.1f}, {hi:.1f}] | {iqm} | {ci} |"
                )
            lines.append("")
        elif domain == "atari":
            lines += [
                "Atari aggregates need random and best-behaviour scores for every game "
                "(rlu/resources/random_scores.json, atari_best_behaviour.json).",
                "",
            ]
        if dom.get("fqe"):
            lines += [
                "Offline policy selection by FQE estimates (data only): the configuration "
                "with the best estimate, scored against the true returns.",
                "",
                "| task | agent | chosen | its return | best return | Spearman | regret@1 |",
                "|---|---|---|---|---|---|---|",
            ]
            for x in dom["fqe"]:
                true = x["true_returns"]
                lines.append(
                    f"| {x['task']} | {x['agent']} | {x['chosen']} | {true[x['chosen']]:.1f} | "
                    f"{max(true.values()):.1f} | {x['spearman']:.2f} | {x['regret_at_1']:.1f} |"
                )
            lines.append("")
        for fig in figures.get(domain, []):
            lines += [f"![{domain}]({fig})", ""]
    return "\n".join(lines)


def _html(markdown: str) -> str:
    """A small Markdown subset (headings, tables, bold, images, paragraphs) as one HTML page."""
    import re

    body, table = [], []

    def inline(text: str) -> str:
        text = html.escape(text)
        return re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", text)

    def flush() -> None:
        if not table:
            return
        rows = [r for r in table if not set(r.replace("|", "").strip()) <= {"-"}]
        out = ["<table>"]
        for i, r in enumerate(rows):
            tag = "th" if i == 0 else "td"
            cells = [c.strip() for c in r.strip().strip("|").split("|")]
            out.append("<tr>" + "".join(f"<{tag}>{inline(c)}</{tag}>" for c in cells) + "</tr>")
        out.append("</table>")
        body.append("\n".join(out))
        table.clear()

    for line in markdown.splitlines():
        if line.startswith("|"):
            table.append(line)
            continue
        flush()
        if line.startswith("## "):
            body.append(f"<h2>{inline(line[3:])}</h2>")
        elif line.startswith("# "):
            body.append(f"<h1>{inline(line[2:])}</h1>")
        elif m := re.match(r"!\[(.*)\]\((.*)\)", line):
            body.append(f'<img src="{html.escape(m[2])}" alt="{html.escape(m[1])}">')
        elif line.strip():
            body.append(f"<p>{inline(line)}</p>")
    flush()
    style = (
        "body{font-family:sans-serif;max-width:1100px;margin:2em auto}"
        "table{border-collapse:collapse;margin:1em 0}"
        "td,th{border:1px solid #bbb;padding:4px 8px;text-align:right}"
        "td:first-child,th:first-child{text-align:left}img{max-width:100%}"
    )
    return (
        "<!doctype html>\n<html><head><meta charset='utf-8'><title>rlu report</title>"
        f"<style>{style}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n"
    )


def _figures(rep: Mapping[str, Any], out: Path) -> dict[str, list[str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figs: dict[str, list[str]] = {}
    (out / "figures").mkdir(parents=True, exist_ok=True)
    for domain, dom in rep["domains"].items():
        rows, agents = dom["online"]["rows"], dom["agents"]
        n = len(rows)
        cols = min(n, 4)
        nrows = -(-n // cols)
        fig, axes = plt.subplots(nrows, cols, figsize=(3.2 * cols, 2.8 * nrows), squeeze=False)
        colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
        for ax, row in zip(axes.flat, rows, strict=False):
            means = [row["cells"].get(a, {}).get("mean", np.nan) for a in agents]
            stds = [row["cells"].get(a, {}).get("std", 0.0) for a in agents]
            x = np.arange(len(agents))
            ax.bar(x, means, yerr=stds, color=[colors[i % len(colors)] for i in x], capsize=3)
            paper_means = [
                ((row["cells"].get(a) or {}).get("paper") or {}).get("mean") for a in agents
            ]
            if any(m is not None for m in paper_means):
                px = [i for i, m in enumerate(paper_means) if m is not None]
                ax.scatter(
                    px,
                    [paper_means[i] for i in px],
                    marker="D",
                    color="k",
                    s=18,
                    zorder=3,
                    label="paper",
                )
            p90 = (dom.get("dataset_p90") or {}).get(row["task"])
            if p90 is not None:
                ax.axhline(p90, color="k", linestyle="--", linewidth=1, label="data p90")
            ax.set_title(row["task"].split("/", 1)[-1], fontsize=9)
            ax.set_xticks(x, [a.split(".")[-1] for a in agents], rotation=30, fontsize=7)
            ax.tick_params(axis="y", labelsize=7)
        for ax in list(axes.flat)[n:]:
            ax.axis("off")
        fig.suptitle(f"{domain}: online policy selection (episode return)", fontsize=10)
        legend: dict[str, Any] = {}
        for ax in axes.flat:  # one legend for the figure, outside the bars
            for h, label in zip(*ax.get_legend_handles_labels(), strict=True):
                legend.setdefault(label, h)
        if legend:
            fig.legend(
                list(legend.values()), list(legend), loc="upper right", fontsize=7, ncol=len(legend)
            )
        fig.tight_layout(rect=(0, 0, 1, 0.94))
        name = f"figures/{domain}_tasks.png"
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        figs[domain] = [name]
        agg = dom.get("aggregates")
        if domain == "atari" and agg:
            names = [a for a in agents if a in agg]
            med = np.array([agg[a]["median"] for a in names])
            lo = np.array([agg[a]["interval_25_75"][0] for a in names])
            hi = np.array([agg[a]["interval_25_75"][1] for a in names])
            fig, ax = plt.subplots(figsize=(1.2 * len(names) + 2, 3))
            ax.bar(names, med, yerr=[med - lo, hi - med], capsize=4)
            ax.set_ylabel("median normalised score (%)")
            ax.set_title("Atari: median over games, [25, 75] bootstrap interval", fontsize=9)
            fig.tight_layout()
            name = "figures/atari_median.png"
            fig.savefig(out / name, dpi=110)
            plt.close(fig)
            figs[domain].append(name)
    return figs


def write_report(
    sweep_dir: str | os.PathLike,
    out: str | os.PathLike | None = None,
    random_scores: Mapping[str, float] | None = None,
    best_behaviour: Mapping[str, float] | None = None,
    figures: bool = True,
) -> list[Path]:
    """Write report.md, report.html, report.json and figures/*.png; return their paths."""
    sweep_dir = Path(sweep_dir)
    results = sweep_dir / "results.jsonl"
    if not results.exists():
        raise RluError(
            f"{results} is missing; run the sweep first (rlu sweep ... --out {sweep_dir})"
        )
    records = [json.loads(x) for x in results.read_text().splitlines() if x.strip()]
    datasets = None
    cfg = sweep_dir / "sweep.json"
    if cfg.exists():
        datasets = json.loads(cfg.read_text()).get("datasets")
    fqe_path = sweep_dir / "fqe.json"
    fqe = json.loads(fqe_path.read_text()) if fqe_path.exists() else None
    rep = build_report(records, datasets, random_scores, best_behaviour, fqe=fqe)
    out = Path(out) if out is not None else sweep_dir / "report"
    out.mkdir(parents=True, exist_ok=True)
    figs = _figures(rep, out) if figures else {}
    md = _markdown(rep, figs)
    paths = [out / "report.md", out / "report.html", out / "report.json"]
    paths[0].write_text(md + "\n")
    paths[1].write_text(_html(md))
    paths[2].write_text(json.dumps(rep, indent=2) + "\n")
    return paths + [out / f for fs in figs.values() for f in fs]
