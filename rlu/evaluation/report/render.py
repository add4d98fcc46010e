"""The rendering of ``rlu report``: the numbers' dict (``rlu.evaluation.report.numbers``) as
Markdown and HTML through Jinja2 templates (``templates/``), and PNG figures through matplotlib.

Each panel of the numbers has one renderer in ``RENDERERS``: ``renderer(dom, domain, figures)``
returns the panel's blocks, ``Text``, ``Table`` and ``Image``, which both templates lay out
(Markdown tables, HTML tables); ``figures`` is None when no PNG is wanted, else it draws and
saves the panel's figures. A panel without a renderer is in report.json only.

Figures use matplotlib's constrained layout with the legend outside the axes, below them, and
titles wrapped to the figure's width: the title of a one-task figure used to run past both
edges, under the legend.

Jinja2 and matplotlib are the ``report`` extra; both are imported when a report is written.
"""

from __future__ import annotations

import textwrap
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rlu.types import RluError, install_hint


# --- blocks ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Text:
    text: str
    kind: str = "text"


@dataclass(frozen=True)
class Cell:
    text: str
    bold: bool = False
    numeric: bool = True


@dataclass(frozen=True)
class Table:
    header: tuple[str, ...]
    rows: tuple[tuple[Cell, ...], ...]
    kind: str = "table"


@dataclass(frozen=True)
class Image:
    path: str
    """Relative to the report's folder."""
    alt: str
    kind: str = "image"


Block = Text | Table | Image


@dataclass(frozen=True)
class Section:
    title: str
    blocks: tuple[Block, ...] = field(default_factory=tuple)


def _fmt(mean: float, std: float) -> str:
    return f"{mean:.1f} ± {std:.1f}"


# --- figures --------------------------------------------------------------------------------
class Figures:
    """Draws with matplotlib (Agg) and saves PNGs under ``out/figures``."""

    DPI = 110

    def __init__(self, out: Path):
        self.out = out
        self.plt = pyplot()
        (out / "figures").mkdir(parents=True, exist_ok=True)

    def save(self, fig: Any, name: str) -> str:
        rel = f"figures/{name}.png"
        fig.savefig(self.out / rel, dpi=self.DPI)
        self.plt.close(fig)
        return rel


def pyplot() -> Any:
    try:
        import matplotlib
    except ImportError:
        raise RluError(f"report figures need matplotlib: {install_hint('report')}") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _wrap(text: str, width_in: float, fontsize: float) -> str:
    """Wrap ``text`` to lines that fit ``width_in`` inches (an average glyph is ~0.6 em)."""
    return textwrap.fill(text, max(12, int(width_in * 72 / (fontsize * 0.6))))


def tasks_figure(dom: Mapping[str, Any], domain: str, plt: Any) -> Any:
    """Per-task bars (agents, ± std over seeds) with the paper's numbers as diamonds and the
    dataset's 90th-percentile return as a dashed line; one legend below every axis."""
    rows, agents = dom["online"]["rows"], dom["agents"]
    n = len(rows)
    cols = min(n, 4)
    nrows = -(-n // cols)
    width = max(3.2 * cols, 6.4)  # room for the title and a one-row legend
    fig = plt.figure(figsize=(width, 2.8 * nrows + 1.0), layout="constrained")
    axes = fig.subplots(nrows, cols, squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    x = np.arange(len(agents))
    for ax, row in zip(axes.flat, rows, strict=False):
        means = [row["cells"].get(a, {}).get("mean", np.nan) for a in agents]
        stds = [row["cells"].get(a, {}).get("std", 0.0) for a in agents]
        ax.bar(x, means, 0.6, yerr=stds, color=[colors[i % len(colors)] for i in x], capsize=3)
        paper = [((row["cells"].get(a) or {}).get("paper") or {}).get("mean") for a in agents]
        px = [i for i, m in enumerate(paper) if m is not None]
        if px:
            ax.scatter(px, [paper[i] for i in px], marker="D", color="k", s=18, zorder=3,
                       label="paper")  # fmt: skip
        p90 = (dom.get("dataset_p90") or {}).get(row["task"])
        if p90 is not None:
            ax.axhline(p90, color="k", linestyle="--", linewidth=1, label="dataset p90")
        ax.set_title(_wrap(row["task"].split("/", 1)[-1], width / cols, 9), fontsize=9)
        ax.set_xticks(x, [a.split(".")[-1] for a in agents], rotation=30, fontsize=7, ha="right")
        ax.set_xlim(-0.75, max(len(agents), 3) - 0.25)
        ax.tick_params(axis="y", labelsize=7)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    # raw returns, as the tables and the paper's appendix (Atari too)
    title = f"{domain}: online policy selection (episode return)"
    fig.suptitle(_wrap(title, width, 10), fontsize=10)
    legend: dict[str, Any] = {}
    for ax in axes.flat:
        for h, label in zip(*ax.get_legend_handles_labels(), strict=True):
            legend.setdefault(label, h)
    if legend:
        fig.legend(list(legend.values()), list(legend), loc="outside lower center",
                   ncol=len(legend), fontsize=7, frameon=False)  # fmt: skip
    return fig


def atari_median_figure(dom: Mapping[str, Any], plt: Any) -> Any:
    agg = dom["aggregates"]
    names = [a for a in dom["agents"] if a in agg]
    med = np.array([agg[a]["median"] for a in names])
    lo = np.array([agg[a]["interval_25_75"][0] for a in names])
    hi = np.array([agg[a]["interval_25_75"][1] for a in names])
    width = max(1.2 * len(names) + 2, 4.8)
    fig, ax = plt.subplots(figsize=(width, 3.2), layout="constrained")
    ax.bar([a.split(".")[-1] for a in names], med, 0.6, yerr=[med - lo, hi - med], capsize=4)
    ax.set_ylabel("median normalised score (%)")
    title = "Atari: median over games, [25, 75] bootstrap interval"
    ax.set_title(_wrap(title, width, 9), fontsize=9)
    return fig


def quickstart_figure(
    policies: Sequence[Mapping[str, Any]], dataset_returns: Sequence[float], title: str, plt: Any
) -> Any:
    """Each policy's mean return (± std over its episodes, its episodes as dots) beside the
    dataset's episode-return distribution, on one shared return axis."""
    fig, (ax, hx) = plt.subplots(
        1, 2, figsize=(8.0, 4.0), sharey=True, width_ratios=(3, 1), layout="constrained"
    )
    x = np.arange(len(policies))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    means = [p["mean"] for p in policies]
    stds = [p["std"] for p in policies]
    ax.bar(x, means, 0.6, yerr=stds, capsize=4, color=[colors[i % len(colors)] for i in x])
    for i, p in enumerate(policies):
        r = np.asarray(p["returns"], np.float64)
        ax.scatter(np.full(len(r), i) + np.linspace(-0.15, 0.15, len(r)), r, s=10, color="k",
                   zorder=3, label="episodes" if i == 0 else None)  # fmt: skip
    returns = np.asarray(dataset_returns, np.float64)
    if len(returns):
        ax.axhline(returns.mean(), color="0.3", linestyle="--", linewidth=1, label="dataset mean")
        hx.hist(returns, bins=min(20, max(5, len(returns) // 2)), orientation="horizontal",
                color="0.6")  # fmt: skip
        hx.axhline(returns.mean(), color="0.3", linestyle="--", linewidth=1)
    ax.set_xticks(x, [p["policy"] for p in policies])
    ax.set_ylabel("episode return")
    ax.set_title("policies (mean ± std over evaluation episodes)", fontsize=9)
    hx.set_title(f"dataset ({len(returns)} episodes)", fontsize=9)
    hx.set_xlabel("episodes")
    hx.xaxis.get_major_locator().set_params(integer=True)  # counts, not 2.5 episodes
    ax.legend(fontsize=7, loc="best")
    fig.suptitle(_wrap(title, 8.0, 10), fontsize=10)
    return fig


# --- renderers, one per panel ----------------------------------------------------------------
Renderer = Callable[[Mapping[str, Any], str, Figures | None], list[Block]]


def _score_table(table: Mapping[str, Any], agents: Sequence[str], with_paper: bool) -> Table:
    head = ["task"]
    for a in agents:
        head += [a, f"{a} (paper)"] if with_paper else [a]
    rows = []
    for row in table["rows"]:
        cells = [Cell(row["task"], numeric=False)]
        for a in agents:
            c = row["cells"].get(a)
            cells.append(
                Cell("", False) if c is None else Cell(_fmt(c["mean"], c["std"]), c["bold"])
            )
            if with_paper:
                p = c.get("paper") if c else None
                cells.append(Cell("" if not p else _fmt(p["mean"], p["std"])))
        rows.append(tuple(cells))
    return Table(tuple(head), tuple(rows))


def _with_paper(dom: Mapping[str, Any]) -> bool:
    return any(c.get("paper") for row in dom["online"]["rows"] for c in row["cells"].values())


def render_online(dom: Mapping[str, Any], domain: str, figures: Figures | None) -> list[Block]:
    with_paper = _with_paper(dom)
    blocks: list[Block] = [
        Text(
            "Online policy selection: episode return, mean ± std over seeds of the best "
            "configuration per task; in bold the best and those whose mean ± std overlaps it."
            + (" The paper's numbers (raw returns) are beside ours." if with_paper else "")
        ),
        _score_table(dom["online"], dom["agents"], with_paper),
    ]
    if figures is not None:
        path = figures.save(tasks_figure(dom, domain, figures.plt), f"{domain}_tasks")
        blocks.append(Image(path, f"{domain}: per-task scores"))
    return blocks


def render_offline_naive(
    dom: Mapping[str, Any], domain: str, figures: Figures | None
) -> list[Block]:
    chosen = ", ".join(f"{a}: {c}" for a, c in dom["offline_naive"]["chosen"].items())
    return [
        Text(
            "Offline policy selection (naive): configuration chosen on the online tasks "
            f"({chosen})."
        ),
        _score_table(dom["offline_naive"], dom["agents"], _with_paper(dom)),
    ]


def render_aggregates(dom: Mapping[str, Any], domain: str, figures: Figures | None) -> list[Block]:
    agg = dom["aggregates"]
    stat = agg["statistic"]
    what = "normalised scores (%)" if dom["normalised"] else "returns"
    rows = []
    for a in dom["agents"]:
        e = agg.get(a)
        if not e:
            continue
        lo, hi = e["interval_25_75"]
        iqm = f"{e['iqm']:.1f}" if "iqm" in e else ""
        ci = f"[{e['iqm_ci95'][0]:.1f}, {e['iqm_ci95'][1]:.1f}]" if "iqm" in e else ""
        texts = [str(e["tasks"]), f"{e[stat]:.1f}", f"[{lo:.1f}, {hi:.1f}]", iqm, ci]
        rows.append((Cell(a, numeric=False), *(Cell(t) for t in texts)))
    blocks: list[Block] = [
        Text(
            f"Aggregate of {what} over tasks: {stat} with bootstrapped [25, 75] interval; IQM "
            "with 95 % stratified bootstrap CI over seeds."
        ),
        Table(("agent", "tasks", stat, "[25, 75]", "IQM", "IQM 95 % CI"), tuple(rows)),
    ]
    if figures is not None and domain == "atari":
        path = figures.save(atari_median_figure(dom, figures.plt), "atari_median")
        blocks.append(Image(path, "Atari: median normalised score"))
    return blocks


def render_fqe(dom: Mapping[str, Any], domain: str, figures: Figures | None) -> list[Block]:
    rows = []
    for x in dom["fqe"]:
        true = x["true_returns"]
        texts = [
            f"{true[x['chosen']]:.1f}",
            f"{max(true.values()):.1f}",
            f"{x['spearman']:.2f}",
            f"{x['regret_at_1']:.1f}",
        ]
        rows.append(
            (
                Cell(x["task"], numeric=False),
                Cell(x["agent"], numeric=False),
                Cell(x["chosen"], numeric=False),
                *(Cell(t) for t in texts),
            )
        )
    head = ("task", "agent", "chosen", "its return", "best return", "Spearman", "regret@1")
    return [
        Text(
            "Offline policy selection by FQE estimates (data only): the configuration with the "
            "best estimate, scored against the true returns."
        ),
        Table(head, tuple(rows)),
    ]


RENDERERS: dict[str, Renderer] = {
    "online": render_online,
    "offline_naive": render_offline_naive,
    "aggregates": render_aggregates,
    "fqe": render_fqe,
}
"""The renderer of each panel of ``rlu.evaluation.report.numbers.PANELS`` that has one."""


def sections(report: Mapping[str, Any], figures: Figures | None) -> list[Section]:
    out = []
    for domain, dom in report["domains"].items():
        blocks: list[Block] = []
        for name in dom.get("panels", []):
            renderer = RENDERERS.get(name)
            if renderer is not None:
                blocks += renderer(dom, domain, figures)
        if domain == "atari" and not dom["normalised"]:
            blocks.append(
                Text(
                    "Atari aggregates need random and best-behaviour scores for every game "
                    "(rlu/resources/random_scores.json, atari_best_behaviour.json)."
                )
            )
        out.append(Section(domain, tuple(blocks)))
    return out


# --- templates ------------------------------------------------------------------------------
def _environment() -> Any:
    try:
        import jinja2
    except ImportError:
        raise RluError(f"rlu report needs Jinja2: {install_hint('report')}") from None
    env = jinja2.Environment(
        loader=jinja2.PackageLoader("rlu.evaluation.report", "templates"),
        autoescape=jinja2.select_autoescape(enabled_extensions=("html.j2",)),
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
        undefined=jinja2.StrictUndefined,
    )
    # a '|' inside a Markdown table cell ends the cell
    env.filters["md_cell"] = lambda s: str(s).replace("|", "\\|")
    return env


def render(template: str, title: str, parts: Sequence[Section]) -> str:
    """Render ``report.md.j2`` or ``report.html.j2`` over the sections."""
    return _environment().get_template(template).render(title=title, sections=parts)
