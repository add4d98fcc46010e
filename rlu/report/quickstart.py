"""The quick start's report: each policy's return beside its dataset's, as a table and a figure.

``rlu quickstart`` is a sweep of a few agents on one dataset plus this one function. The table
says what produced every number (preset, learner steps, evaluation episodes, the data's
command) and sets the paper's numbers for the task apart: the quick start's small presets on
laptop-scale data are not the paper's setting, so they are not comparable to them.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rlu.files import atomic_path, write_atomic, write_json
from rlu.system import install_hint

MARKER = "results.json"
"""The file every quick-start folder holds (the quick start replaces only such a folder)."""


def paper_line(task_id: str) -> str:
    """The paper's numbers on the task, ``"BC 386, D4PG 856, ..."`` in its table's order (its
    "DM Control suite results" table for the bundled task: the paper's settings and networks on
    the release's data; it states no continuous step budget); "" where the paper has none."""
    from rlu.report.numbers import paper_row

    return ", ".join(f"{a} {e['mean']:g}" for a, e in paper_row(task_id).items())


def _std(x: np.ndarray) -> float | None:
    """The sample std (ddof 1), the report's one spread; None for one value."""
    return float(x.std(ddof=1)) if x.size > 1 else None


def policy_row(name: str, returns: Sequence[float], **made: Any) -> dict[str, Any]:
    """One table row: the policy's returns and what produced them (``made``: preset, steps);
    ``std`` the sample std (ddof 1) over its evaluation episodes."""
    r = np.asarray(returns, np.float64)
    return {
        "policy": name,
        "mean": float(r.mean()),
        "std": _std(r),
        "returns": r.tolist(),
        **made,
    }


def _against_bc(rows: Sequence[Mapping[str, Any]], task_id: str) -> list[str]:
    """The paper's first control-suite comparison, offline RL against BC, on these runs."""
    bc = next((r for r in rows if r["policy"] == "bc"), None)
    others = [r for r in rows if r["policy"] not in ("random", "bc")]
    if bc is None or not others or bc["mean"] <= 0:
        return []
    best = max(others, key=lambda r: r["mean"])
    lines = [
        f"Best offline RL agent here: {best['policy']}, {best['mean'] / bc['mean']:.2f} "
        "times BC's return."
    ]
    paper = paper_line(task_id)
    if paper:
        lines.append(
            f"The paper on this task ({paper}; the paper's settings on the release's "
            "data) is not comparable to these runs (small presets, short budgets, laptop-scale "
            "data): it says only which way the comparison went there."
        )
    return [*lines, ""]


def write_quickstart_report(
    out: str | Path,
    task_id: str,
    dataset: str | Path,
    command: str,
    dataset_returns: Sequence[float] | np.ndarray,
    rows: Sequence[Mapping[str, Any]],
    seconds: float,
) -> str:
    """Write OUT/report.md, OUT/results.json and (with matplotlib) OUT/quickstart.png; returns
    the Markdown text."""
    out = Path(out)
    returns = np.asarray(dataset_returns, np.float64)
    mean, std = float(returns.mean()), _std(returns)
    p90 = float(np.percentile(returns, 90))
    trained = [r for r in rows if r.get("steps") is not None]
    made = {(r.get("preset"), r.get("steps"), r.get("eval_episodes")) for r in trained}
    lines = [
        f"# rlu quickstart: {task_id}",
        "",
        f"Dataset: `{dataset}` ({len(returns)} episodes, made by `{command}`).",
    ]
    if len(made) == 1:
        preset, steps, episodes = made.pop()
        lines.append(
            f"Each agent: {preset} preset, {steps:,} learner steps; every policy "
            f"evaluated on {episodes} env episodes."
        )
    lines += [
        "",
        "| policy | preset, steps | mean return | sample std (ddof 1) | / dataset mean | "
        "beats the data |",
        "|---|---|---:|---:|---:|---|",
    ]
    for r in rows:
        beats = "yes" if r["mean"] > mean else "no"
        how = f"{r['preset']}, {r['steps']:,}" if r.get("steps") is not None else "-"
        lines.append(
            f"| {r['policy']} | {how} | {r['mean']:.1f} | {_num(r['std'])} | "
            f"{r['mean'] / mean:.2f} | {beats} |"
        )
    lines += [
        f"| *dataset* (p90 {p90:.1f}) | | {mean:.1f} | {_num(std)} | 1.00 | |",
        "",
        *_against_bc(rows, task_id),
        f"Dataset returns: mean {mean:.1f}, p90 {p90:.1f}, min {returns.min():.1f}, "
        f"max {returns.max():.1f}.",
        "",
    ]
    figure = _figure(rows, returns, task_id, out / "quickstart.png")
    if figure is not None:
        lines += [f"![policies beside the dataset's returns]({figure.name})", ""]
    text = "\n".join(lines)
    write_atomic(out / "report.md", text)
    write_json(
        out / MARKER,
        {
            "task": task_id,
            "dataset": str(dataset),
            "policies": list(rows),
            "seconds": seconds,
            "dataset_returns": {"episodes": len(returns), "mean": mean, "std": std, "p90": p90},
        },
    )
    return text


def _num(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def _figure(
    rows: Sequence[Mapping[str, Any]], returns: np.ndarray, task_id: str, path: Path
) -> Path | None:
    """Draw the figure; None (and a note) without matplotlib."""
    if importlib.util.find_spec("matplotlib") is None:
        print(f"  (no figure: it needs matplotlib, {install_hint('report')})")
        return None
    from rlu.report.render import pyplot, quickstart_figure

    plt = pyplot()
    title = f"rlu quickstart: {task_id}, policies beside the dataset's episode returns"
    fig = quickstart_figure(rows, returns, title, plt)
    try:
        with atomic_path(path, suffix=True) as tmp:
            fig.savefig(tmp, dpi=110)
    finally:
        plt.close(fig)
    return path
