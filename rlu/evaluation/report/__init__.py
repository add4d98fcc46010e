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
from collections.abc import Mapping
from pathlib import Path

from rlu.evaluation.report.numbers import (
    PANELS,
    DomainContext,
    build_report,
    dataset_percentile,
    load_paper_results,
    paper_entry,
    task_info,
)
from rlu.types import RluError

__all__ = [
    "PANELS",
    "DomainContext",
    "build_report",
    "dataset_percentile",
    "load_paper_results",
    "paper_entry",
    "task_info",
    "write_report",
]


def write_report(
    sweep_dir: str | os.PathLike,
    out: str | os.PathLike | None = None,
    random_scores: Mapping[str, float] | None = None,
    best_behaviour: Mapping[str, float] | None = None,
    figures: bool = True,
) -> list[Path]:
    """Write report.md, report.html, report.json and figures/*.png; return their paths."""
    from rlu.evaluation.report import render

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
    parts = render.sections(rep, render.Figures(out) if figures else None)
    paths = [out / "report.md", out / "report.html", out / "report.json"]
    paths[0].write_text(render.render("report.md.j2", "rlu report", parts))
    paths[1].write_text(render.render("report.html.j2", "rlu report", parts))
    paths[2].write_text(json.dumps(rep, indent=2) + "\n")
    images = [b.path for s in parts for b in s.blocks if isinstance(b, render.Image)]
    return paths + [out / p for p in images]
