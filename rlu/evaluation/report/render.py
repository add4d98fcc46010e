"""The rendering of ``rlu report``: the numbers' dict (``rlu.evaluation.report.numbers``) as
Markdown and HTML through Jinja2 templates (``templates/``), and PNG figures through matplotlib.

Each panel of the numbers has one renderer in ``RENDERERS``: ``renderer(dom, domain, figures)``
returns the panel's blocks, ``Text``, ``Table`` and ``Image``, which both templates lay out
(Markdown tables, HTML tables); ``figures`` is None when no PNG is wanted, else it draws and
saves the panel's figures. A panel without a renderer is in report.json only; a panel the
numbers left out (``dom["absent"]``) is one line naming it (``TITLES``) and why.

The paper's figures: ``tasks_figure`` (control suite / locomotion per-task bars, online tasks
above offline ones), ``atari_median_figure`` (two panels, online and naive offline selection),
``atari_per_game_figure`` (one row per agent) and ``sensitivity_figure`` (IQN tau, BCQ
threshold).

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


def _cell_text(cell: Mapping[str, Any], most: int) -> str:
    """mean ± std; a cell of fewer seeds than the table's most says how many (one: no std)."""
    n = len(cell["seeds"])
    text = _fmt(cell["mean"], cell["std"]) if n > 1 else f"{cell['mean']:.1f}"
    return text + (f" ({n} seed{'s' if n > 1 else ''})" if n < most else "")


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


def _legend_below(fig: Any, axes: Sequence[Any], ncol: int = 3) -> None:
    """One legend for every axis, outside the axes, below them, at most ``ncol`` entries a
    row."""
    legend: dict[str, Any] = {}
    for ax in axes:
        for h, label in zip(*ax.get_legend_handles_labels(), strict=True):
            legend.setdefault(label, h)
    if legend:
        fig.legend(list(legend.values()), list(legend), loc="outside lower center",
                   ncol=min(len(legend), ncol), fontsize=7, frameon=False)  # fmt: skip


def _agent_colors(agents: Sequence[str], plt: Any) -> dict[str, str]:
    """One colour per agent, the same in every axis and figure of a domain."""
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    return {a: colors[i % len(colors)] for i, a in enumerate(agents)}


def _short(agent: str) -> str:
    return agent.split(".")[-1]


SELECTION_TITLES = {
    "online": "online policy selection",
    "offline": "offline policy selection (naive: the configuration chosen on the online tasks)",
}


def tasks_figure(dom: Mapping[str, Any], domain: str, plt: Any) -> Any:
    """The paper's control suite / locomotion figure: per-task bars (agents, ± std over seeds),
    the online-selection tasks under online selection above the offline-selection tasks under
    naive offline selection, the paper's numbers as diamonds and the dataset's 90th-percentile
    return as a dashed line; one legend below every axis."""
    bars, agents = dom["task_bars"], dom["agents"]
    groups = [(g, bars[g]) for g in ("online", "offline") if bars[g]]
    cols = min(max(len(rows) for _, rows in groups), 4)
    heights = [-(-len(rows) // cols) for _, rows in groups]
    width = max(3.2 * cols, 6.4)  # room for the title and a one-row legend
    fig = plt.figure(figsize=(width, 2.9 * sum(heights) + 1.0), layout="constrained")
    subs = fig.subfigures(len(groups), 1, height_ratios=heights, squeeze=False)[:, 0]
    color = _agent_colors(agents, plt)
    x = np.arange(len(agents))
    every = []
    for sub, (group, rows), h in zip(subs, groups, heights, strict=True):
        axes = sub.subplots(h, cols, squeeze=False)
        every += list(axes.flat)
        for ax, row in zip(axes.flat, rows, strict=False):
            means = [row["cells"].get(a, {}).get("mean", np.nan) for a in agents]
            stds = [row["cells"].get(a, {}).get("std", 0.0) for a in agents]
            ax.bar(x, means, 0.6, yerr=stds, color=[color[a] for a in agents], capsize=3)
            paper = [row["paper"].get(a, {}).get("mean") for a in agents]
            px = [i for i, m in enumerate(paper) if m is not None]
            if px:
                ax.scatter(px, [paper[i] for i in px], marker="D", color="k", s=18, zorder=3,
                           label="paper")  # fmt: skip
            p90 = (dom.get("dataset_p90") or {}).get(row["task"])
            if p90 is not None:
                ax.axhline(p90, color="k", linestyle="--", linewidth=1, label="dataset p90")
            ax.set_title(_wrap(row["task"].split("/", 1)[-1], width / cols, 9), fontsize=9)
            ax.set_xticks(x, [_short(a) for a in agents], rotation=30, fontsize=7, ha="right")
            ax.set_xlim(-0.75, max(len(agents), 3) - 0.25)
            ax.tick_params(axis="y", labelsize=7)
        for ax in list(axes.flat)[len(rows) :]:
            ax.axis("off")
        axes[0, 0].set_ylabel("episode return", fontsize=8)
        sub.suptitle(_wrap(SELECTION_TITLES[group], width, 9), fontsize=9, style="italic")
    # raw returns, as the tables and the paper's appendix
    title = f"{domain}: episode return per task (mean ± std over seeds)"
    fig.suptitle(_wrap(title, width, 10), fontsize=10)
    _legend_below(fig, every)
    return fig


def atari_median_figure(dom: Mapping[str, Any], plt: Any) -> Any:
    """The paper's Atari figure: median normalised score per agent with the bootstrapped
    [25, 75] interval, online policy selection (tuning games) beside naive offline selection
    (held-out games); the paper's table normalised the same way as diamonds."""
    panel, agents = dom["atari_median"], dom["agents"]
    halves = [h for h in ("online", "offline") if h in panel]
    color = _agent_colors(agents, plt)
    width = max(1.0 * len(agents) + 2.0, 4.0) * len(halves)
    fig, axes = plt.subplots(
        1, len(halves), figsize=(width, 3.8), layout="constrained", squeeze=False
    )
    for ax, h in zip(axes[0], halves, strict=True):
        half = panel[h]
        names = [a for a in agents if a in half["agents"]]
        e = [half["agents"][a] for a in names]
        med = np.array([c["median"] for c in e])
        lo = np.array([c["interval_25_75"][0] for c in e])
        hi = np.array([c["interval_25_75"][1] for c in e])
        x = np.arange(len(names))
        ax.bar(x, med, 0.6, yerr=[med - lo, hi - med], capsize=4,
               color=[color[a] for a in names])  # fmt: skip
        for i, m in enumerate(med):
            ax.annotate(f"{m:.1f}", (i, hi[i]), xytext=(0, 2), textcoords="offset points",
                        ha="center", va="bottom", fontsize=7)  # fmt: skip
        paper = [c["paper_same_games"] for c in e]
        px = [i for i, p in enumerate(paper) if p is not None]
        if px:
            ax.scatter(px, [paper[i] for i in px], marker="D", color="k", s=18, zorder=3,
                       label="paper's table, same games, normalised")  # fmt: skip
        ax.axhline(100.0, color="0.4", linestyle=":", linewidth=1,
                   label="best behaviour snapshot (100 %)")  # fmt: skip
        ax.axhline(0.0, color="k", linewidth=0.6)
        ax.set_xticks(x, [_short(a) for a in names], fontsize=8)
        ax.set_xlim(-0.75, max(len(names), 3) - 0.25)
        ax.set_ylabel("median normalised score (%)", fontsize=8)
        ax.tick_params(axis="y", labelsize=7)
        what = "tuning" if h == "online" else "held-out"
        head = "online policy selection" if h == "online" else "offline policy selection (naive)"
        sub = f"{len(half['games'])} of {half['of']} {what} games"
        ax.set_title(_wrap(f"{head}: {sub}", width / len(halves), 9), fontsize=9)
    title = "Atari: median normalised score over games, bootstrapped [25, 75] interval"
    fig.suptitle(_wrap(title, width, 10), fontsize=10)
    _legend_below(fig, list(axes[0]))
    return fig


def atari_per_game_figure(dom: Mapping[str, Any], plt: Any) -> Any:
    """The paper's appendix figure "Atari normalized performance": per agent (one row each),
    each game's normalised improvement over the best behaviour snapshot, best first, on a
    symmetric log axis (improvements span -100 to thousands); the paper's table as diamonds."""
    per = dom["atari_per_game"]["agents"]
    names = [a for a in dom["agents"] if a in per]
    most = max(len(per[a]) for a in names)
    width = max(6.4, 0.32 * most + 2.0)
    fig, axes = plt.subplots(
        len(names), 1, figsize=(width, 2.6 * len(names) + 1.0), layout="constrained",
        squeeze=False,
    )  # fmt: skip
    for ax, a in zip(axes[:, 0], names, strict=True):
        bars = per[a]
        x = np.arange(len(bars))
        imp = np.array([b["improvement"] for b in bars])
        ax.bar(x, imp, 0.7, color=np.where(imp >= 0, "tab:green", "tab:red"))
        paper = [b["paper_improvement"] for b in bars]
        px = [i for i, p in enumerate(paper) if p is not None]
        if px:
            ax.scatter(px, [paper[i] for i in px], marker="D", color="k", s=16, zorder=3,
                       label="paper's table, normalised")  # fmt: skip
        ax.axhline(0.0, color="k", linewidth=0.8)
        # linear over [-100, 100] (random .. twice the best snapshot), logarithmic beyond: a
        # few games improve by thousands of per cent
        ax.set_yscale("symlog", linthresh=100.0, linscale=2.0)
        seen = [*imp, *(p for p in paper if p is not None), -100.0, 100.0]
        ax.set_ylim(_symlog_pad(min(seen)), _symlog_pad(max(seen)))
        ax.yaxis.set_major_formatter(plt.FuncFormatter(lambda v, _: f"{v:g}"))
        labels = [
            b["task"].split("/", 1)[-1]
            + (" *" if b["selection"] == "online" else "")
            + (" †" if dom.get("reference_flags", {}).get(b["task"]) else "")
            for b in bars
        ]
        ax.set_xticks(x, labels, rotation=60, fontsize=7, ha="right")
        ax.set_xlim(-0.75, max(len(bars), 3) - 0.25)
        ax.tick_params(axis="y", labelsize=7)
        ax.set_ylabel("improvement (%)", fontsize=8)
        ax.set_title(f"{_short(a)}", fontsize=9)
    title = "Atari: per-game improvement over the best behaviour snapshot (normalised score - 100)"
    note = "* tuning game (online policy selection); others held-out (naive offline selection)"
    if any(dom.get("reference_flags", {}).values()):
        note += "; † small denominator (best - random under 2 random stds)"
    fig.suptitle(_wrap(title, width, 10) + "\n" + _wrap(note, width, 8), fontsize=10)
    _legend_below(fig, list(axes[:, 0]))
    return fig


def _symlog_pad(v: float) -> float:
    """An axis limit a little beyond ``v`` on a symlog axis with linthresh 100."""
    return v * 1.15 if abs(v) <= 100.0 else v * 2.0


def sensitivity_figure(panel: Mapping[str, Any], title: str, plt: Any) -> Any:
    """The paper's ablation figures: per value of one hyper-parameter, the median normalised
    score over the tuning games as a dark square with the [25, 75] interval; the value the
    paper found best shaded."""
    vals = panel["values"]
    x = np.arange(len(vals))
    med = np.array([v["median"] for v in vals])
    lo = np.array([v["interval_25_75"][0] for v in vals])
    hi = np.array([v["interval_25_75"][1] for v in vals])
    width = max(4.8, 1.1 * len(vals) + 2.4)
    fig, ax = plt.subplots(figsize=(width, 3.6), layout="constrained")
    best = panel["paper"]["best"]
    for i, v in enumerate(vals):
        if v["value"] == best:
            ax.axvspan(i - 0.35, i + 0.35, color="tab:orange", alpha=0.2, linewidth=0,
                       label="the paper's best value (its figure has no numbers)")  # fmt: skip
    ax.errorbar(x, med, yerr=[med - lo, hi - med], fmt="s", color="0.15", markersize=7,
                capsize=4, label="median over tuning games, [25, 75] interval")  # fmt: skip
    for i, m in enumerate(med):
        ax.annotate(f"{m:.1f}", (i, m), xytext=(8, 0), textcoords="offset points",
                    va="center", fontsize=7)  # fmt: skip
    ax.set_xticks(x, [str(v["value"]) for v in vals], fontsize=8)
    ax.set_xlim(-0.75, len(vals) - 0.25)
    ax.set_xlabel(panel["field"], fontsize=8)
    ax.set_ylabel("median normalised score (%)", fontsize=8)
    ax.tick_params(axis="y", labelsize=7)
    sub = f"online policy selection, {len(panel['games'])} of {panel['of']} tuning games"
    fig.suptitle(_wrap(f"{title} ({sub})", width, 10), fontsize=10)
    _legend_below(fig, [ax], ncol=1)  # two long entries side by side overrun a narrow figure
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
    # a sweep still running (or cut short) has cells of fewer seeds: those say how many
    most = max((len(c["seeds"]) for r in table["rows"] for c in r["cells"].values()), default=0)
    for row in table["rows"]:
        cells = [Cell(row["task"], numeric=False)]
        for a in agents:
            c = row["cells"].get(a)
            cells.append(Cell("", False) if c is None else Cell(_cell_text(c, most), c["bold"]))
            if with_paper:
                p = row["paper"].get(a)
                cells.append(Cell("" if p is None else _fmt(p["mean"], p["std"])))
        rows.append(tuple(cells))
    return Table(tuple(head), tuple(rows))


def _with_paper(dom: Mapping[str, Any]) -> bool:
    return any(row["paper"] for row in dom["online"]["rows"])


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
    return blocks


def render_offline_naive(
    dom: Mapping[str, Any], domain: str, figures: Figures | None
) -> list[Block]:
    chosen = ", ".join(f"{a}: {c}" for a, c in dom["offline_naive"]["chosen"].items())
    return [
        Text(
            "Offline policy selection (naive): configuration chosen on the online tasks "
            f"({chosen})." + _skipped(dom["offline_naive"]["skipped"])
        ),
        _score_table(dom["offline_naive"], dom["agents"], _with_paper(dom)),
    ]


def _skipped(skipped: Mapping[str, str]) -> str:
    return "".join(f" Left out: {why}." for why in skipped.values())


def _small_denominators(dom: Mapping[str, Any], tasks: Sequence[str]) -> str:
    """The games of ``tasks`` whose normaliser is small (``rlu.evaluation.reference``), marked †."""
    from rlu.evaluation.reference import SPREAD_K

    games = [t.split("/", 1)[-1] for t in tasks if dom.get("reference_flags", {}).get(t)]
    return (f" † small denominator (best - random < {SPREAD_K:g} x the random returns' std): "
            f"{', '.join(games)}; their normalised scores mostly measure random play's spread."
            if games else "")  # fmt: skip


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
        iqm = ci = ""
        if "iqm" in e:
            iqm = f"{e['iqm']:.1f} ({e['iqm_seeds']} seed{'s' * (e['iqm_seeds'] > 1)})"
            if e["iqm_ci95"] is not None:
                ci = f"[{e['iqm_ci95'][0]:.1f}, {e['iqm_ci95'][1]:.1f}]"
        texts = [str(e["tasks"]), f"{e[stat]:.1f}", f"[{lo:.1f}, {hi:.1f}]", iqm, ci]
        rows.append((Cell(a, numeric=False), *(Cell(t) for t in texts)))
    blocks: list[Block] = [
        Text(
            f"Aggregate of {what} over tasks: {stat} with bootstrapped [25, 75] interval; IQM "
            "over the seeds every task has, with 95 % stratified bootstrap CI over those seeds "
            "(none with one seed)."
        ),
        Table(("agent", "tasks", stat, "[25, 75]", "IQM", "IQM 95 % CI"), tuple(rows)),
    ]
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


def render_task_bars(dom: Mapping[str, Any], domain: str, figures: Figures | None) -> list[Block]:
    bars = dom["task_bars"]
    chosen = ", ".join(f"{a}: {c}" for a, c in bars["chosen"].items())
    text = (
        "Per-task episode return as the paper draws its control suite and locomotion figures: "
        "the online-selection tasks under online policy selection"
        + (
            f", the offline-selection tasks under naive offline selection ({chosen})"
            if bars["offline"]
            else ""
        )
        + "; bars mean ± std over seeds (the numbers are the tables' above), diamonds the "
        "paper's, dashed lines the dataset's 90th-percentile episode return."
        + _skipped(bars["skipped"])
    )
    blocks: list[Block] = [Text(text)]
    p90 = dom.get("dataset_p90") or {}
    if any(v is not None for v in p90.values()):
        rows = [
            (Cell(row["task"], numeric=False), Cell(sel, numeric=False),
             Cell("" if p90.get(row["task"]) is None else f"{p90[row['task']]:.1f}"))
            for sel in ("online", "offline") for row in bars[sel]
        ]  # fmt: skip
        blocks.append(Table(("task", "selection", "dataset p90 return"), tuple(rows)))
    if figures is not None and (bars["online"] or bars["offline"]):
        path = figures.save(tasks_figure(dom, domain, figures.plt), f"{domain}_tasks")
        blocks.append(Image(path, f"{domain}: per-task scores"))
    return blocks


def _pct(x: float | None) -> str:
    return "" if x is None else f"{x:.1f}"


def render_atari_median(
    dom: Mapping[str, Any], domain: str, figures: Figures | None
) -> list[Block]:
    panel = dom["atari_median"]
    rows = []
    for h, label in (("online", "online (tuning games)"), ("offline", "naive offline (held-out)")):
        half = panel.get(h)
        if half is None:
            continue
        for a in dom["agents"]:
            e = half["agents"].get(a)
            if e is None:
                continue
            lo, hi = e["interval_25_75"]
            texts = [
                f"{e['games']} of {half['of']}",
                f"{e['median']:.1f}",
                f"[{lo:.1f}, {hi:.1f}]",
                _pct(e["paper_same_games"]),
                _pct(e["paper_all_games"]),
            ]
            rows.append((Cell(label, numeric=False), Cell(a, numeric=False),
                         *(Cell(t) for t in texts)))  # fmt: skip
    text = (
        "The paper's Atari figure: median normalised score over games (%) with a bootstrapped "
        "[25, 75] interval, online policy selection on the tuning games and naive offline "
        "selection on the held-out games"
        + (
            " (configuration chosen on the tuning games: "
            + ", ".join(f"{a}: {c}" for a, c in panel["offline"]["chosen"].items())
            + ")"
            if "offline" in panel
            else ""
        )
        + f". A game missing from the sweep is left out. Note: {panel['note']}."
        + "".join(f" {h}: left out, {why}." for h, why in panel["missing"].items())
        + _skipped(panel.get("offline", {}).get("skipped", {}))
        + _small_denominators(dom, dom["tasks"])
    )
    head = ("selection", "agent", "games", "median", "[25, 75]", "paper (table), same games",
            "paper (table), all games")  # fmt: skip
    blocks: list[Block] = [Text(text), Table(head, tuple(rows))]
    if figures is not None:
        path = figures.save(atari_median_figure(dom, figures.plt), "atari_median")
        blocks.append(Image(path, "Atari: median normalised score, online and offline selection"))
    return blocks


def render_atari_per_game(
    dom: Mapping[str, Any], domain: str, figures: Figures | None
) -> list[Block]:
    panel = dom["atari_per_game"]
    agents = [a for a in dom["agents"] if a in panel["agents"]]
    by = {a: {b["task"]: b for b in panel["agents"][a]} for a in agents}
    head = ["game", "selection"]
    for a in agents:
        head += [a, f"{a} (paper)"]
    rows = []
    for task in dom["tasks"]:
        if not any(task in by[a] for a in agents):
            continue
        mark = " †" if dom.get("reference_flags", {}).get(task) else ""
        cells = [Cell(task + mark, numeric=False), Cell(task_selection(task), numeric=False)]
        for a in agents:
            b = by[a].get(task)
            cells += [
                Cell("" if b is None else f"{b['improvement']:+.1f}", bold=bool(b and
                     b["improvement"] >= 0)),
                Cell("" if b is None or b["paper_improvement"] is None
                     else f"{b['paper_improvement']:+.1f}"),
            ]  # fmt: skip
        rows.append(tuple(cells))
    text = (
        "The paper's appendix figure (Atari normalized performance): per game and agent, the "
        "normalised score improvement over the best behaviour snapshot (normalised score - 100, "
        "in %; 0: as good as the best snapshot, -100: random), each game under its own "
        "protocol; in bold an improvement. Note: the paper prints this figure without numbers; "
        "'paper' is its per-game appendix table normalised with the reference scores used here."
        + _skipped(panel["skipped"])
        + _small_denominators(dom, dom["tasks"])
    )
    blocks: list[Block] = [Text(text), Table(tuple(head), tuple(rows))]
    if figures is not None:
        path = figures.save(atari_per_game_figure(dom, figures.plt), "atari_per_game")
        blocks.append(Image(path, "Atari: per-game normalised improvement"))
    return blocks


def task_selection(task: str) -> str:
    from rlu.evaluation.report.numbers import task_info

    return task_info(task)[1]


SENSITIVITY_TITLES = {
    "iqn_tau": "IQN: number of tau samples",
    "bcq_threshold": "BCQ (discrete): threshold",
}


def _sensitivity_renderer(name: str) -> Renderer:
    def render_sensitivity(
        dom: Mapping[str, Any], domain: str, figures: Figures | None
    ) -> list[Block]:
        panel = dom[name]
        paper = panel["paper"]
        rows = tuple(
            (Cell(str(v["value"]), numeric=False), Cell(f"{v['games']} of {panel['of']}"),
             Cell(f"{v['median']:.1f}"),
             Cell(f"[{v['interval_25_75'][0]:.1f}, {v['interval_25_75'][1]:.1f}]"))
            for v in panel["values"]
        )  # fmt: skip
        text = (
            f"{SENSITIVITY_TITLES[name]} (the paper's appendix ablation): median normalised "
            f"score (%) over the tuning games per value of {panel['field']}, each game's other "
            "hyper-parameters chosen by online policy selection, with a bootstrapped [25, 75] "
            f"interval. The paper draws this figure without numbers over the grid "
            f"{paper['grid']} and found {paper['best']} best."
        )
        head = (panel["field"], "games", "median", "[25, 75]")
        blocks: list[Block] = [Text(text), Table(head, rows)]
        if figures is not None:
            fig = sensitivity_figure(panel, SENSITIVITY_TITLES[name], figures.plt)
            blocks.append(Image(figures.save(fig, name), SENSITIVITY_TITLES[name]))
        return blocks

    return render_sensitivity


RENDERERS: dict[str, Renderer] = {
    "online": render_online,
    "offline_naive": render_offline_naive,
    "aggregates": render_aggregates,
    "fqe": render_fqe,
    "task_bars": render_task_bars,
    "atari_median": render_atari_median,
    "atari_per_game": render_atari_per_game,
    "iqn_tau": _sensitivity_renderer("iqn_tau"),
    "bcq_threshold": _sensitivity_renderer("bcq_threshold"),
}
"""The renderer of each panel of ``rlu.evaluation.report.numbers.PANELS`` that has one."""

TITLES = {
    "online": "Online policy selection",
    "offline_naive": "Offline policy selection (naive)",
    "aggregates": "Aggregates over tasks",
    "fqe": "Offline policy selection by FQE",
    "dataset_p90": "Dataset 90th-percentile returns",
    "task_bars": "Per-task figure",
    "atari_median": "Atari median normalised score (the paper's Atari figure)",
    "atari_per_game": "Atari per-game normalised improvement",
    "iqn_tau": "IQN tau-samples sensitivity",
    "bcq_threshold": "BCQ threshold sensitivity",
}
"""Each panel's name in the line that says why it is left out."""


def sections(report: Mapping[str, Any], figures: Figures | None) -> list[Section]:
    out = []
    for domain, dom in report["domains"].items():
        blocks: list[Block] = []
        for name in dom.get("panels", []):
            renderer = RENDERERS.get(name)
            if renderer is not None:
                blocks += renderer(dom, domain, figures)
        for name, why in dom.get("absent", {}).items():
            blocks.append(Text(f"{TITLES.get(name, name)}: left out, {why}."))
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
