"""``rlu report SWEEP_DIR``: the paper's tables and figures from a sweep's results, as Markdown,
HTML, PNG and JSON (the numbers the tables print).

Two halves: ``numbers`` computes every number (a pure function of the sweep's records, one dict,
written as report.json) and ``render`` lays them out (Markdown and HTML through Jinja2
templates, PNG through matplotlib). A new panel is one function in ``numbers.PANELS`` and one
renderer in ``render.RENDERERS``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from rlu import runs
from rlu.evaluation.report.numbers import (
    CHALLENGE_MARK,
    DATA_SOURCES,
    PANELS,
    Absent,
    DomainContext,
    PaperSteps,
    build_report,
    dataset_percentile,
    load_paper_results,
    not_comparable,
    paper_entry,
    report_key,
    run_provenance,
    task_info,
)
from rlu.types import RluError

__all__ = [
    "DATA_SOURCES",
    "PANELS",
    "Absent",
    "DomainContext",
    "PaperSteps",
    "build_report",
    "dataset_percentile",
    "load_paper_results",
    "not_comparable",
    "paper_entry",
    "run_provenance",
    "task_info",
    "write_report",
]


def write_report(
    sweep_dir: str | os.PathLike | Sequence[str | os.PathLike],
    out: str | os.PathLike | None = None,
    random_scores: Mapping[str, float] | None = None,
    best_behaviour: Mapping[str, float] | None = None,
    figures: bool = True,
    paper_steps: PaperSteps | None = None,
) -> list[Path]:
    """Write report.md, report.html, report.json and figures/*.png; return their paths.

    ``sweep_dir`` is one sweep folder or several (an Atari sweep and a control suite sweep
    run different agents, so the paper's figures come from more than one sweep); their
    records are reported together, and ``out`` is then required. ``paper_steps(agent,
    discrete)`` is the learner budget of an agent's paper preset (``build_report``): the
    caller's, since this package does not import the agents; without it no cell is comparable
    with the paper's numbers."""
    from rlu.evaluation.report import render

    dirs = [Path(sweep_dir)] if isinstance(sweep_dir, str | os.PathLike) else [
        Path(d) for d in sweep_dir
    ]  # fmt: skip
    if not dirs:
        raise RluError("no sweep folder given; pass one or more SWEEP_DIR")
    if out is None and len(dirs) > 1:
        raise RluError(f"{len(dirs)} sweep folders: pass --out for the report folder")
    records, datasets, fqe = _read_sweeps(dirs)
    rep = build_report(
        records, datasets, random_scores, best_behaviour, fqe=fqe, paper_steps=paper_steps
    )
    out = Path(out) if out is not None else dirs[0] / "report"
    out.mkdir(parents=True, exist_ok=True)
    parts = render.sections(rep, render.Figures(out) if figures else None)
    paths = [out / "report.md", out / "report.html", out / "report.json"]
    paths[0].write_text(render.render("report.md.j2", "rlu report", parts))
    paths[1].write_text(render.render("report.html.j2", "rlu report", parts))
    paths[2].write_text(json.dumps(rep, indent=2) + "\n")
    images = [b.path for s in parts for b in s.blocks if isinstance(b, render.Image)]
    return paths + [out / p for p in images]


def _read_sweeps(
    dirs: Sequence[Path],
) -> tuple[list[dict[str, Any]], dict[str, str] | None, dict[str, Any] | None]:
    """(records, datasets by task, FQE selections) of one or more sweep folders; a run of the
    same (task, agent, config, seed) in two of them, or one task with two datasets, is an
    error (the report would pick one silently)."""
    records: list[dict[str, Any]] = []
    seen: dict[tuple[str, str, str, int], Path] = {}
    datasets: dict[str, str] = {}
    where: dict[str, Path] = {}
    selections: list[dict[str, Any]] = []
    any_datasets = any_fqe = False
    for d in dirs:
        results = d / runs.RESULTS
        cfg = d / runs.SWEEP_CONFIG
        sweep_datasets = runs.load_sweep_config(d)["datasets"] if cfg.exists() else {}
        any_datasets = any_datasets or cfg.exists()
        for r in runs.load_results(d):
            # RWRL results under a challenge are their own task (report_key), as in the paper
            r = {**r, "task": report_key(r)}
            key = (r["task"], r["agent"], r["config"], int(r["seed"]))
            if key in seen:
                raise RluError(
                    f"{results}: run {key} is also in {seen[key] / runs.RESULTS}; report "
                    "sweeps that do not overlap, or one of them"
                )
            seen[key] = d
            records.append(r)
            path = sweep_datasets.get(key[0].partition(CHALLENGE_MARK)[0])
            if path is None:
                continue
            task = key[0]
            if task in datasets and datasets[task] != path:
                raise RluError(
                    f"{cfg}: task {task} has dataset {path}, but "
                    f"{where[task] / runs.SWEEP_CONFIG} has {datasets[task]}; report sweeps of "
                    "one dataset per task"
                )
            datasets[task], where[task] = path, d
        fqe_path = d / runs.FQE
        if fqe_path.exists():
            any_fqe = True
            selections += runs.read_fqe(d)["selections"]
    fqe = {"selections": selections} if any_fqe else None
    return records, datasets if any_datasets else None, fqe
