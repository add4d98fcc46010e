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

# --- blocks ---------------------------------------------------------------------------------
from rlu.domains import DOMAINS
from rlu.system import install_hint
from rlu.types import RluError


@dataclass(frozen=True)
class Text:
    text: str
    kind: str = "text"


@dataclass(frozen=True)
class Cell:
    text: str
    bold: bool = False
    numeric: bool = True
    note: str = ""
    """Words after the number (whether it compares with the paper's): Markdown puts them on
    the same line, HTML on a line of their own under it."""


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


SPREAD = "± sample std (ddof 1) over seeds"
"""How every ± of rlu's numbers in a report is computed, as captions name it."""


def _fmt(mean: float, std: float | None) -> str:
    return f"{mean:.1f}" if std is None else f"{mean:.1f} ± {std:.1f}"


def _cell_text(cell: Mapping[str, Any], most: int, tags: str = "") -> str:
    """mean ± sample std; a cell of one seed is its mean and says "1 seed" (it has no spread),
    one of fewer seeds than the table's most says how many; ``tags``: the cell's provenance
    letters, where the domain has several."""
    n = len(cell["seeds"])
    text = _fmt(cell["mean"], cell["std"])
    if n == 1 or n < most:
        text += f" ({n} seed{'s' * (n != 1)})"
    return text + tags


def comparable_label(number: Mapping[str, Any]) -> str:
    """ "(comparable)", or "(not comparable: preset, budget, ...)": the conditions of the
    paper's number this one misses."""
    if number["comparable"]:
        return "(comparable)"
    return f"(not comparable: {', '.join(number['missing'])})"


# --- what produced a number -------------------------------------------------------------------
def steps_text(n: int | None) -> str:
    """2_000_000 -> '2M', 20_000 -> '20k', 300 -> '300' (None: 'unknown')."""
    if n is None:
        return "unknown"
    for size, unit in ((1_000_000, "M"), (1_000, "k")):
        if n >= size:
            return f"{n / size:.{0 if n % size == 0 else 1}f}{unit}"
    return str(n)


def data_text(data: Mapping[str, Any]) -> str:
    """A run's data (its record's ``data``) in words."""
    source = data["source"]
    steps = f"{data['steps']:,} steps" if data.get("steps") is not None else ""
    if source == "release":
        family, files, shards = data.get("family"), data.get("files"), data.get("shards")
        held = ""
        if shards and shards.get("of"):
            held = f"{shards['used']} of its {shards['of']} shards"
        elif files:
            held = f"{files} files" + (", none named as a release shard" if shards else "")
        parts = [f"family {family}" if family else "", held, steps]
        detail = ", ".join(p for p in parts if p)
        return "the release's files" + (f" ({detail})" if detail else "")
    if source == "generated":
        detail = ", ".join(
            x
            for x in (
                f"scale {data['scale']}" if data.get("scale") else "",
                f"`{_command(data['command'])}`" if data.get("command") else "",
            )
            if x
        )
        detail = ", ".join(x for x in (detail, steps) if x)
        return "generated by rlu" + (f" ({detail})" if detail else "")
    if source == "imported":
        return (
            "imported"
            + (f" from {data['format']}" if data.get("format") else "")
            + (f" ({steps})" if steps else "")
        )
    if source == "synthetic":
        return "synthetic (random test data" + (f", {steps})" if steps else ")")
    return "unknown (not recorded by this run)"


def _command(command: Any) -> str:
    return " ".join(map(str, command)) if isinstance(command, list | tuple) else str(command)


def provenance_text(p: Mapping[str, Any]) -> str:
    """One provenance entry (``numbers.run_provenance``) in words."""
    steps = p["steps"]
    learner = "learner steps unknown" if steps is None else f"{steps:,} learner steps"
    if p.get("pretrain_steps"):
        learner += f" (+{p['pretrain_steps']:,} pre-training)"
    n = p["eval_episodes"]
    episodes = (
        "evaluation episodes unknown"
        if n is None
        else f"{n} evaluation episode{'s' * (n != 1)} per run"
    )
    return f"preset {p['preset'] or 'unknown'}, {learner}, data {data_text(p['data'])}, {episodes}"


def _count(n: int, what: str) -> str:
    return f"{n} {what}{'s' * (n != 1)}"


def _label(i: int) -> str:
    return chr(ord("A") + i) if i < 26 else f"P{i}"


def _tags(dom: Mapping[str, Any], sources: Sequence[int]) -> str:
    """' [A]' (or ' [A, B]'): the provenance of a number, where the domain has several."""
    if len(dom.get("provenance", [])) < 2:
        return ""
    return " [" + ", ".join(_label(i) for i in sources) + "]"


def produced_by(dom: Mapping[str, Any], sources: Sequence[int] | None = None) -> str:
    """What produced the numbers of a table (``sources``: its provenance entries; None: all the
    domain's) as one sentence: spelled out when the domain has one, else a legend of the
    letters its cells carry."""
    entries = dom.get("provenance", [])
    idx = sorted(set(range(len(entries)) if sources is None else sources))
    if not idx:
        return ""
    if len(entries) == 1:
        return f"Every number here: {provenance_text(entries[0])}."
    return (
        "Produced by: "
        + "; ".join(f"[{_label(i)}] {provenance_text(entries[i])}" for i in idx)
        + "."
    )


def provenance_summary(dom: Mapping[str, Any], sources: Sequence[int] | None = None) -> str:
    """A short line for a figure: each field's values over the entries (``sources``)."""
    entries = dom.get("provenance", [])
    idx = sorted(set(range(len(entries)) if sources is None else sources))
    picked = [entries[i] for i in idx]

    def values(f: Callable[[Mapping[str, Any]], str]) -> str:
        return "/".join(dict.fromkeys(f(p) for p in picked))

    return (
        f"preset {values(lambda p: str(p['preset'] or 'unknown'))}, "
        f"{values(lambda p: steps_text(p['steps']))} learner steps, "
        f"data {values(lambda p: _data_short(p['data']))}, "
        f"{values(lambda p: str(p['eval_episodes'] or 'unknown'))} evaluation episodes per run"
    )


def _data_short(data: Mapping[str, Any]) -> str:
    """A run's data source, with the release shards it holds where it is the release's."""
    shards = data.get("shards") or {}
    if data["source"] == "release" and shards.get("of"):
        return f"release ({shards['used']} of {shards['of']} shards)"
    return str(data["source"])


def paper_source(dom: Mapping[str, Any], agents: Sequence[str]) -> str:
    """Where the paper's numbers come from and the budget the paper states for them: credited
    with nothing it does not state (no learner budget for the continuous baselines)."""
    states = dom.get("paper_states") or {}
    table = states.get("table") or "the paper's appendix tables"
    budget = states.get("budget", {}).get("paper")
    steps = (
        f"{steps_text(budget)} learner steps"
        if budget is not None
        else "the paper states no budget"
    )
    return f"{table}; {steps}"


def compared_at(dom: Mapping[str, Any], agents: Sequence[str]) -> str:
    """The budget rlu's comparable cells ran, named as the paper's or as rlu's."""
    budgets = {dom.get("paper_presets", {}).get(a, {}).get("budget") for a in agents}
    budgets.discard(None)
    stated = all(dom.get("paper_presets", {}).get(a, {}).get("budget_stated") for a in agents)
    if not budgets:
        return ""
    at = "/".join(steps_text(b) for b in sorted(budgets))
    return f" at the paper's {at}" if stated else f" at rlu's {at} steps"


def paper_head(name: str, dom: Mapping[str, Any], agents: Sequence[str], status: str) -> str:
    """The heading of a column of the paper's numbers: where they come from, the budget the
    paper states for them (or that it states none), and whether the cells beside them meet
    every condition of the paper's number (``status``: ``all``, ``some`` or ``none`` of them
    do); where the paper states no budget, a comparison is made at rlu's and says so."""
    head = f"{name}: paper ({paper_source(dom, agents)})"
    if status == "all":
        return head + ": comparable" + compared_at(dom, agents)
    if status == "some":
        return head + ": comparable only where marked" + compared_at(dom, agents)
    return head + ": not comparable to these cells"


def _sources_of(table: Mapping[str, Any]) -> list[int]:
    return sorted({i for r in table["rows"] for c in r["cells"].values() for i in c["provenance"]})


# --- figures --------------------------------------------------------------------------------
class Figures:
    """Draws with matplotlib (Agg) and saves PNGs under ``out/figures``."""

    DPI = 110

    def __init__(self, out: Path):
        from rlu.files import make_folder

        self.out = out
        self.plt = pyplot()
        make_folder(out / "figures", root=out)

    def save(self, fig: Any, name: str) -> str:
        """Write ``fig`` as figures/NAME.png through a checked temporary (``rlu.files``)."""
        from rlu.files import atomic_path

        rel = f"figures/{name}.png"
        try:
            with atomic_path(self.out / rel, suffix=True, root=self.out) as tmp:
                fig.savefig(tmp, dpi=self.DPI)
        finally:
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
        ncol = min(len(legend), ncol)
        width = fig.get_figwidth() / ncol - 0.5  # inches per entry, less the marker
        labels = [_wrap(label, width, 7) for label in legend]
        fig.legend(
            list(legend.values()),
            labels,
            loc="outside lower center",
            ncol=ncol,
            fontsize=7,
            frameon=False,
        )


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
    """The paper's control suite / locomotion figure: per-task bars (agents, ± sample std over
    seeds; a bar of one seed hatched, without an error bar, "1" above it), the online-selection
    tasks under online selection above the offline-selection tasks under naive offline
    selection, the paper's numbers as diamonds and the dataset's 90th-percentile return as a
    dashed line; one legend below every axis. Each bar carries the letter of what produced it
    (the tables' letters) where the domain has several, and the title says what each letter
    (or, with one, every bar) used: preset, learner steps, data, evaluation episodes."""
    bars, agents = dom["task_bars"], dom["agents"]
    groups = [(g, bars[g]) for g in ("online", "offline") if bars[g]]
    cols = min(max(len(rows) for _, rows in groups), 4)
    heights = [-(-len(rows) // cols) for _, rows in groups]
    width = max(3.2 * cols, 6.4)  # room for the title and a one-row legend
    fig = plt.figure(figsize=(width, 2.9 * sum(heights) + 1.0), layout="constrained")
    subs = fig.subfigures(len(groups), 1, height_ratios=heights, squeeze=False)[:, 0]
    color = _agent_colors(agents, plt)
    x = np.arange(len(agents))
    beside = [
        c for _, rows in groups for r in rows for a, c in r["cells"].items() if a in r["paper"]
    ]
    paper_label = _paper_marker(dom, beside)
    every = []
    for sub, (group, rows), h in zip(subs, groups, heights, strict=True):
        axes = sub.subplots(h, cols, squeeze=False)
        every += list(axes.flat)
        for ax, row in zip(axes.flat, rows, strict=False):
            _bars(ax, dom, row["cells"], agents, color)
            paper = [row["paper"].get(a, {}).get("mean") for a in agents]
            px = [i for i, m in enumerate(paper) if m is not None]
            if px:
                ax.scatter(
                    px,
                    [paper[i] for i in px],
                    marker="D",
                    color="k",
                    s=18,
                    zorder=3,
                    label=paper_label,
                )
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
    title = f"{domain}: episode return per task (mean {SPREAD})"
    sources = sorted(
        {
            i
            for _, rows in groups
            for r in rows
            for c in r["cells"].values()
            for i in c["provenance"]
        }
    )
    fig.suptitle(
        _wrap(title, width, 10) + "\n" + _wrap(_bars_line(dom, sources), width, 10), fontsize=10
    )
    _legend_below(fig, every, ncol=2)
    return fig


def _bars(
    ax: Any,
    dom: Mapping[str, Any],
    cells: Mapping[str, Any],
    agents: Sequence[str],
    color: Mapping[str, str],
) -> None:
    """One task's bars: mean ± sample std; a cell of one seed hatched without an error bar
    (it has no spread) and "1" written above it; where the domain has several provenance
    entries, each bar's letters above it."""
    x = np.arange(len(agents))
    means = [cells.get(a, {}).get("mean", np.nan) for a in agents]
    spread = [cells.get(a, {}).get("std") for a in agents]
    one = [a in cells and len(cells[a]["seeds"]) == 1 for a in agents]
    ax.bar(
        x,
        means,
        0.6,
        color=[color[a] for a in agents],
        hatch=["//" if o else None for o in one],
        edgecolor="white",
    )
    with_std = [i for i, v in enumerate(spread) if v is not None]
    if with_std:
        ax.errorbar(
            x[with_std],
            [means[i] for i in with_std],
            [spread[i] for i in with_std],
            fmt="none",
            ecolor="k",
            capsize=3,
            linewidth=1,
        )
    if any(one):
        ax.bar(
            [np.nan],
            [np.nan],
            color="0.7",
            hatch="//",
            edgecolor="white",
            label="one seed: no spread",
        )
    several = len(dom.get("provenance", [])) > 1
    for i, a in enumerate(agents):
        if a not in cells:
            continue
        c = cells[a]
        text = ",".join(_label(j) for j in c["provenance"]) if several else ""
        text = " ".join(t for t in ("1" if one[i] else "", text) if t)
        if text:
            top = c["mean"] + (c["std"] or 0.0)
            ax.annotate(
                text,
                (i, max(top, 0.0)),
                xytext=(0, 2),
                textcoords="offset points",
                ha="center",
                va="bottom",
                fontsize=6,
            )


def _bars_line(dom: Mapping[str, Any], sources: Sequence[int]) -> str:
    """What produced the bars: every bar's settings spelled out where one entry drew them all;
    else what the bars share, then what each letter's entry adds (the bars carry the letters)."""
    entries = dom.get("provenance", [])
    if len(entries) < 2:
        return f"every bar: {provenance_summary(dom, sources)}"
    parts = {i: provenance_parts(entries[i]) for i in sources}
    keys = list(next(iter(parts.values()))) if parts else []
    shared = [k for k in keys if len({parts[i][k] for i in parts}) == 1]
    head = ", ".join(parts[sources[0]][k] for k in shared if parts[sources[0]][k])
    each = "; ".join(
        f"[{_label(i)}] " + (", ".join(p[k] for k in keys if k not in shared and p[k]) or "-")
        for i, p in parts.items()
    )
    return (f"every bar: {head}; " if head else "") + each


def provenance_parts(p: Mapping[str, Any]) -> dict[str, str]:
    """One provenance entry in a figure's few words, field by field: preset, learner steps,
    pre-training, data (with the release's shards, or the command that generated it),
    evaluation episodes."""
    data = p["data"]
    what = _data_short(data)
    if data["source"] == "generated" and data.get("command"):
        what += f" by `{_command(data['command'])}`"
    episodes = "unknown" if p["eval_episodes"] is None else p["eval_episodes"]
    pretrain = p["pretrain_steps"]
    return {
        "preset": f"preset {p['preset'] or 'unknown'}",
        "steps": f"{steps_text(p['steps'])} steps",
        "pretrain": f"+{steps_text(pretrain)} pre-training" if pretrain else "",
        "data": f"{what} data",
        "episodes": f"{episodes} episodes",
    }


def _paper_marker(dom: Mapping[str, Any], beside: Sequence[Mapping[str, Any]]) -> str:
    """The legend of the paper's markers in a figure: where they come from, the budget the
    paper states (or that it states none), and whether the bars beside them meet every
    condition of the paper's numbers."""
    status = _status([c["comparable"] for c in beside])
    verdict = {"all": "comparable", "some": "comparable only where the tables say so"}.get(
        status, "not comparable to these bars"
    )
    return f"paper ({paper_source(dom, dom['agents'])}): {verdict}"


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
        ax.bar(x, med, 0.6, yerr=[med - lo, hi - med], capsize=4, color=[color[a] for a in names])
        for i, m in enumerate(med):
            ax.annotate(
                f"{m:.1f}" + _tags(dom, e[i]["provenance"]),
                (i, hi[i]),
                xytext=(0, 2),
                textcoords="offset points",
                ha="center",
                va="bottom",
                fontsize=7,
            )
        paper = [c["paper_same_games"] for c in e]
        px = [i for i, p in enumerate(paper) if p is not None]
        if px:
            label = _paper_marker(dom, [e[i] for i in px]).replace(
                "paper (", "paper's table, same games, normalised (", 1
            )
            ax.scatter(
                px, [paper[i] for i in px], marker="D", color="k", s=18, zorder=3, label=label
            )
        ax.axhline(
            100.0, color="0.4", linestyle=":", linewidth=1, label="best behaviour snapshot (100 %)"
        )
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
    sources = sorted(
        {i for h in halves for e in panel[h]["agents"].values() for i in e["provenance"]}
    )
    fig.suptitle(
        _wrap(title, width, 10) + "\n" + _wrap(_bars_line(dom, sources), width, 10), fontsize=10
    )
    _legend_below(fig, list(axes[0]), ncol=1)
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
        len(names),
        1,
        figsize=(width, 2.6 * len(names) + 1.0),
        layout="constrained",
        squeeze=False,
    )
    for ax, a in zip(axes[:, 0], names, strict=True):
        bars = per[a]
        x = np.arange(len(bars))
        imp = np.array([b["improvement"] for b in bars])
        ax.bar(x, imp, 0.7, color=np.where(imp >= 0, "tab:green", "tab:red"))
        paper = [b["paper_improvement"] for b in bars]
        px = [i for i, p in enumerate(paper) if p is not None]
        if px:
            label = _paper_marker(dom, [bars[i] for i in px]).replace(
                "paper (", "paper's table, normalised (", 1
            )
            ax.scatter(
                px, [paper[i] for i in px], marker="D", color="k", s=16, zorder=3, label=label
            )
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
            + _tags(dom, b["provenance"])
            for b in bars
        ]
        ax.set_xticks(x, labels, rotation=60, fontsize=7, ha="right")
        ax.set_xlim(-0.75, max(len(bars), 3) - 0.25)
        ax.tick_params(axis="y", labelsize=7)
        ax.set_ylabel("improvement (%)", fontsize=8)
        ax.set_title(f"{_short(a)}", fontsize=9)
    title = "Atari: per-game improvement over the best behaviour snapshot (normalised score - 100)"
    note = "* tuning game (online policy selection); others held-out (naive offline selection)"
    sources = sorted({i for a in names for b in per[a] for i in b["provenance"]})
    note += "; " + _bars_line(dom, sources)
    if any(dom.get("reference_flags", {}).values()):
        note += "; † small denominator (best - random under 2 random stds)"
    fig.suptitle(_wrap(title, width, 10) + "\n" + _wrap(note, width, 10), fontsize=10)
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
            ax.axvspan(
                i - 0.35,
                i + 0.35,
                color="tab:orange",
                alpha=0.2,
                linewidth=0,
                label="the paper's best value (its figure has no numbers)",
            )
    ax.errorbar(
        x,
        med,
        yerr=[med - lo, hi - med],
        fmt="s",
        color="0.15",
        markersize=7,
        capsize=4,
        label="median over tuning games, [25, 75] interval",
    )
    for i, m in enumerate(med):
        ax.annotate(
            f"{m:.1f}", (i, m), xytext=(8, 0), textcoords="offset points", va="center", fontsize=7
        )
    ax.set_xticks(x, [str(v["value"]) for v in vals], fontsize=8)
    ax.set_xlim(-0.75, len(vals) - 0.25)
    ax.set_xlabel(panel["field"], fontsize=8)
    ax.set_ylabel("median normalised score (%)", fontsize=8)
    ax.tick_params(axis="y", labelsize=7)
    sub = f"online policy selection, {len(panel['games'])} of {panel['of']} tuning games"
    fig.suptitle(_wrap(f"{title} ({sub})", width, 10), fontsize=10)
    _legend_below(fig, [ax], ncol=1)  # two long entries side by side overrun a narrow figure
    return fig


def curves_figure(dom: Mapping[str, Any], domain: str, plt: Any) -> Any:
    """Learning curves, one axis per task: per agent (its colour) every seed's evaluation
    return as a thin line and their mean as a thick one with a band of ± the sample std over
    seeds (ddof 1; none with one seed), at the steps every seed evaluated; a dotted line where
    a pre-training phase ends."""
    panel, agents = dom["curves"], dom["agents"]
    tasks = panel["tasks"]
    cols = min(len(tasks), 3)
    rows_n = -(-len(tasks) // cols)
    width = max(3.6 * cols, 6.4)
    fig, axes = plt.subplots(
        rows_n, cols, figsize=(width, 2.9 * rows_n + 1.4), layout="constrained", squeeze=False
    )
    color = _agent_colors(agents, plt)
    for ax, t in zip(axes.flat, tasks, strict=False):
        for a, c in t["agents"].items():
            for i, seed in enumerate(c["seeds"]):
                ax.plot(
                    seed["steps"],
                    seed["means"],
                    color=color[a],
                    linewidth=0.7,
                    alpha=0.45,
                    label="one seed" if i == 0 else None,
                )
            mean = np.asarray(c["mean"], np.float64)
            ax.plot(
                c["steps"],
                mean,
                color=color[a],
                linewidth=2.0,
                label=f"{_short(a)} ({_count(c['n_seeds'], 'seed')})",
                marker="o" if len(c["steps"]) == 1 else None,
                markersize=4,
            )
            if c["std"] is not None:
                std = np.asarray(c["std"], np.float64)
                ax.fill_between(
                    c["steps"], mean - std, mean + std, color=color[a], alpha=0.18, linewidth=0
                )
            if c["pretrain_steps"]:
                ax.axvline(
                    c["pretrain_steps"],
                    color=color[a],
                    linestyle=":",
                    linewidth=1,
                    label="pre-training ends",
                )
        ax.set_title(_wrap(t["task"].split("/", 1)[-1], width / cols, 9), fontsize=9)
        ax.set_xlabel("learner steps", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.xaxis.get_offset_text().set_fontsize(7)
    for ax in list(axes.flat)[len(tasks) :]:
        ax.axis("off")
    for ax in axes[:, 0]:
        ax.set_ylabel("evaluation return", fontsize=8)
    sources = sorted({i for t in tasks for a in t["agents"] for i in _cell_of(dom, t["task"], a)})
    title = (
        f"{domain}: learning curves of the configurations the tables show; thin: each "
        f"seed, thick: their mean, band: {SPREAD} (none with one seed)"
    )
    fig.suptitle(
        _wrap(title, width, 10)
        + "\n"
        + _wrap(_bars_line(dom, sources), width, 9).replace("every bar", "every curve"),
        fontsize=10,
    )
    _legend_below(fig, list(axes.flat), ncol=3)
    return fig


def _cell_of(dom: Mapping[str, Any], task: str, agent: str) -> list[int]:
    """The provenance entries of a task and agent's cell, from the tables."""
    for name in ("online", "offline_naive"):
        for row in (dom.get(name) or {}).get("rows", []):
            if row["task"] == task and agent in row["cells"]:
                return row["cells"][agent]["provenance"]
    return list(range(len(dom.get("provenance", []))))


PROFILE_SPLITS = {
    "online": "online policy selection, online-selection tasks",
    "offline": "naive offline selection, offline-selection tasks",
}


def profiles_figure(dom: Mapping[str, Any], plt: Any) -> Any:
    """rliable's performance profiles, one axis per split: per agent the fraction of its
    (seed, task) runs scoring above tau, with the 95 % stratified bootstrap confidence band
    over seeds (none with one seed)."""
    splits = dom["profiles"]["splits"]
    names = list(splits)
    width = max(4.6 * len(names), 6.4)
    fig, axes = plt.subplots(
        1, len(names), figsize=(width, 3.9), layout="constrained", squeeze=False
    )
    color = _agent_colors(dom["agents"], plt)
    score = "normalised score (%)" if dom["normalised"] else "episode return"
    for ax, split in zip(axes[0], names, strict=True):
        half = splits[split]
        tau = np.asarray(half["tau"])
        for a, e in half["agents"].items():
            ax.plot(
                tau,
                e["fraction"],
                color=color[a],
                linewidth=2,
                label=f"{_short(a)} ({_count(len(e['seeds']), 'seed')})",
            )
            if e["ci"] is not None:
                ax.fill_between(tau, e["ci"][0], e["ci"][1], color=color[a], alpha=0.2, linewidth=0)
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel(f"{score} (tau)", fontsize=8)
        ax.set_ylabel("fraction of runs scoring > tau", fontsize=8)
        ax.grid(True, alpha=0.2)
        ax.tick_params(labelsize=7)
        sub = f"{PROFILE_SPLITS[split]}: {_count(len(half['tasks']), 'task')}"
        ax.set_title(_wrap(sub, width / len(names), 9), fontsize=9)
    title = (
        "Performance profiles (as rliable computes them): the fraction of each agent's "
        "runs scoring above tau; band: 95 % stratified bootstrap CI over seeds (none with "
        "one seed)"
    )
    sources = sorted({i for h in splits.values() for i in h["provenance"]})
    fig.suptitle(
        _wrap(title, width, 10)
        + "\n"
        + _wrap(_bars_line(dom, sources), width, 9).replace("every bar", "every run"),
        fontsize=10,
    )
    _legend_below(fig, list(axes[0]), ncol=4)
    return fig


def improvement_figure(dom: Mapping[str, Any], plt: Any) -> Any:
    """The probability of improvement (rliable's numbers, drawn as rliable draws them): per pair
    of agents, P(X > Y) as a black tick with its 95 % stratified bootstrap confidence interval
    as a bar (none where both agents have one seed); 0.5 dotted."""
    splits = dom["improvement"]["splits"]
    names = list(splits)
    most = max(len(splits[n]["pairs"]) for n in names)
    width = max(4.6 * len(names), 6.4)
    fig, axes = plt.subplots(
        1, len(names), figsize=(width, 0.45 * most + 2.4), layout="constrained", squeeze=False
    )
    color = _agent_colors(dom["agents"], plt)
    for ax, split in zip(axes[0], names, strict=True):
        pairs = splits[split]["pairs"]
        y = np.arange(len(pairs))[::-1]
        for yi, pr in zip(y, pairs, strict=True):
            if pr["ci"] is not None:
                lo, hi = pr["ci"]
                ax.barh(yi, hi - lo, 0.6, left=lo, color=color[pr["x"]], alpha=0.7)
            ax.vlines(pr["probability"], yi - 0.3, yi + 0.3, color="k", linewidth=2.5)
            # the number beside its tick, on the side with room (an interval of zero width,
            # from runs that all agree, is no bar: the number says it)
            ci = "" if pr["ci"] is None else f" [{pr['ci'][0]:.2f}, {pr['ci'][1]:.2f}]"
            left = pr["probability"] > 0.5
            ax.annotate(
                f"{pr['probability']:.2f}{ci}",
                (pr["probability"], yi + 0.32),
                xytext=(-3 if left else 3, 0),
                textcoords="offset points",
                ha="right" if left else "left",
                va="bottom",
                fontsize=7,
            )
        ax.axvline(0.5, color="0.4", linestyle=":", linewidth=1)
        ax.set_yticks(y, [f"P({_short(p['x'])} > {_short(p['y'])})" for p in pairs], fontsize=7)
        ax.set_xlim(-0.02, 1.02)
        ax.set_ylim(-0.6, len(pairs) - 0.1)
        ax.set_xlabel("probability of improvement", fontsize=8)
        ax.tick_params(axis="x", labelsize=7)
        sub = f"{PROFILE_SPLITS[split]}: {_count(len(splits[split]['tasks']), 'task')}"
        ax.set_title(_wrap(sub, width / len(names), 9), fontsize=9)
    title = (
        "Probability of improvement (as rliable computes it): P(X > Y), a run of X "
        "scoring above one of Y on a task, averaged over tasks; bar: 95 % stratified "
        "bootstrap CI over seeds (none where both have one seed)"
    )
    sources = sorted({i for h in splits.values() for i in h["provenance"]})
    fig.suptitle(
        _wrap(title, width, 10)
        + "\n"
        + _wrap(_bars_line(dom, sources), width, 9).replace("every bar", "every run"),
        fontsize=10,
    )
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
    stds = [np.nan if p["std"] is None else p["std"] for p in policies]  # one episode: no bar
    ax.bar(x, means, 0.6, yerr=stds, capsize=4, color=[colors[i % len(colors)] for i in x])
    for i, p in enumerate(policies):
        r = np.asarray(p["returns"], np.float64)
        ax.scatter(
            np.full(len(r), i) + np.linspace(-0.15, 0.15, len(r)),
            r,
            s=10,
            color="k",
            zorder=3,
            label="episodes" if i == 0 else None,
        )
    returns = np.asarray(dataset_returns, np.float64)
    if len(returns):
        ax.axhline(returns.mean(), color="0.3", linestyle="--", linewidth=1, label="dataset mean")
        hx.hist(
            returns, bins=min(20, max(5, len(returns) // 2)), orientation="horizontal", color="0.6"
        )
        hx.axhline(returns.mean(), color="0.3", linestyle="--", linewidth=1)
    ax.set_xticks(x, [p["policy"] for p in policies])
    ax.set_ylabel("episode return")
    ax.set_title("policies (mean ± sample std over evaluation episodes)", fontsize=9)
    hx.set_title(f"dataset ({len(returns)} episodes)", fontsize=9)
    hx.set_xlabel("episodes")
    hx.xaxis.get_major_locator().set_params(integer=True)  # counts, not 2.5 episodes
    ax.legend(fontsize=7, loc="best")
    fig.suptitle(_wrap(title, 8.0, 10), fontsize=10)
    return fig


# --- renderers, one per panel ----------------------------------------------------------------
Renderer = Callable[[Mapping[str, Any], str, Figures | None], list[Block]]


def _score_table(dom: Mapping[str, Any], table: Mapping[str, Any]) -> Table:
    """Task x agent; where the paper has numbers, each agent's column of them beside its own,
    headed with the settings they come from and whether these cells share them."""
    agents = dom["agents"]
    with_paper = _with_paper(table)
    cols = table.get("paper_columns", {})
    head = ["task"]
    for a in agents:
        head.append(a)
        if with_paper:
            col = cols.get(a)
            head.append(paper_head(a, dom, [a], col["comparable"]) if col else f"{a}: paper (none)")
    rows = []
    # a sweep still running (or cut short) has cells of fewer seeds: those say how many
    most = max((len(c["seeds"]) for r in table["rows"] for c in r["cells"].values()), default=0)
    for row in table["rows"]:
        cells = [Cell(row["task"], numeric=False)]
        for a in agents:
            c = row["cells"].get(a)
            if c is None:
                cells.append(Cell("", False))
            else:
                beside = a in row["paper"]
                text = _cell_text(c, most, _tags(dom, c["provenance"]))
                # beside the paper's number: whether it compares and, if not, what it misses
                note = comparable_label(c) if beside else ""
                cells.append(Cell(text, c["bold"], note=note))
            if with_paper:
                p = row["paper"].get(a)
                cells.append(Cell("" if p is None else _fmt(p["mean"], p["std"])))
        rows.append(tuple(cells))
    return Table(tuple(head), tuple(rows))


def _with_paper(table: Mapping[str, Any]) -> bool:
    return any(row["paper"] for row in table["rows"])


def _paper_note(dom: Mapping[str, Any], table: Mapping[str, Any]) -> str:
    """Why the cells beside the paper's numbers are labelled as they are: per condition of the
    paper's number, the reasons the cells give for missing it."""
    if not _with_paper(table):
        return ""
    cells = [c for r in table["rows"] for a, c in r["cells"].items() if a in r["paper"]]
    text = (
        f" The paper's numbers (raw returns; {paper_source(dom, dom['agents'])}) stand in "
        "their own columns; each of rlu's cells beside one says (comparable) only when every "
        "condition of the paper's number holds, else which it misses"
    )
    why = missing_reasons(cells)
    if not why:
        return text + "; every cell here meets them all."
    return text + ": " + "; ".join(f"{c}: {' / '.join(r)}" for c, r in why.items()) + "."


def missing_reasons(numbers: Sequence[Mapping[str, Any]]) -> dict[str, list[str]]:
    """Per condition some of ``numbers`` miss, their distinct reasons."""
    out: dict[str, list[str]] = {}
    for n in numbers:
        for c in n["missing"]:
            for reason in str(n["conditions"][c]).split("; "):
                if reason not in out.setdefault(c, []):
                    out[c].append(reason)
    return out


def _chosen_text(panel: Mapping[str, Any]) -> str:
    only = set(panel.get("only_configuration", []))
    return ", ".join(
        f"{a}: {c}" + (" (its only configuration)" if a in only else "")
        for a, c in panel["chosen"].items()
    )


def render_online(dom: Mapping[str, Any], domain: str, figures: Figures | None) -> list[Block]:
    table = dom["online"]
    return [
        Text(
            "Online policy selection, over the online-selection tasks only: episode return, "
            f"mean {SPREAD} of the configuration with the best mean per task (a cell of one "
            "seed is its mean and says so: it has no spread); in bold the best and those whose "
            "mean ± std overlaps it. "
            + produced_by(dom, _sources_of(table))
            + _paper_note(dom, table)
        ),
        _score_table(dom, table),
    ]


def render_offline_naive(
    dom: Mapping[str, Any], domain: str, figures: Figures | None
) -> list[Block]:
    panel = dom["offline_naive"]
    stat = DOMAINS[domain].statistic if domain in DOMAINS else "mean"
    return [
        Text(
            "Offline policy selection (the paper's naive selection), over the offline-selection "
            f"tasks only: one configuration per agent, the one with the best {stat} over this "
            f"sweep's online-selection tasks, applied unchanged ({_chosen_text(panel)}). "
            + produced_by(dom, _sources_of(panel))
            + _paper_note(dom, panel)
            + _skipped(panel["skipped"])
        ),
        _score_table(dom, panel),
    ]


def _skipped(skipped: Mapping[str, str]) -> str:
    return "".join(f" Left out: {why}." for why in skipped.values())


def _small_denominators(dom: Mapping[str, Any], tasks: Sequence[str]) -> str:
    """The games of ``tasks`` whose normaliser is small (``rlu.evaluation.reference``), marked †."""
    from rlu.evaluation.reference import SPREAD_K

    games = [t.split("/", 1)[-1] for t in tasks if dom.get("reference_flags", {}).get(t)]
    return (
        f" † small denominator (best - random < {SPREAD_K:g} x the random returns' std): "
        f"{', '.join(games)}; their normalised scores mostly measure random play's spread."
        if games
        else ""
    )


AGGREGATE_SPLITS = {
    "online": "online policy selection, online-selection tasks",
    "offline": "naive offline selection, offline-selection tasks",
}


def render_aggregates(dom: Mapping[str, Any], domain: str, figures: Figures | None) -> list[Block]:
    agg = dom["aggregates"]
    stat = agg["statistic"]
    what = "normalised scores (%)" if dom["normalised"] else "returns"
    rows = []
    sources: set[int] = set()
    for split, label in AGGREGATE_SPLITS.items():
        half = agg.get(split)
        if half is None:
            continue
        for a in dom["agents"]:
            e = half["agents"].get(a)
            if not e:
                continue
            sources.update(e["provenance"])
            lo, hi = e["interval_25_75"]
            # one task: nothing to resample, so no interval (it would be [x, x])
            spread = f"[{lo:.1f}, {hi:.1f}]" if e["tasks"] > 1 else "(one task)"
            iqm = ci = ""
            if "iqm" in e:
                iqm = f"{e['iqm']:.1f} ({e['iqm_seeds']} seed{'s' * (e['iqm_seeds'] > 1)})"
                if e["iqm_ci95"] is not None:
                    ci = f"[{e['iqm_ci95'][0]:.1f}, {e['iqm_ci95'][1]:.1f}]"
            texts = [str(e["tasks"]), f"{e[stat]:.1f}", spread, iqm, ci]
            rows.append(
                (
                    Cell(label, numeric=False),
                    Cell(a + _tags(dom, e["provenance"]), numeric=False),
                    *(Cell(t) for t in texts),
                )
            )
    chosen = ""
    if "offline" in agg:
        chosen = f"; here {_chosen_text(agg['offline'])}"
    text = (
        f"Aggregate of {what} over tasks, each split under its own protocol and never mixed: "
        f"online policy selection (best configuration per task) over the online-selection "
        f"tasks; the paper's naive offline selection over the offline-selection tasks (one "
        f"configuration per agent, the best {stat} over the online-selection tasks{chosen}). "
        f"{stat.capitalize()} with a bootstrapped [25, 75] percentile interval over tasks "
        "(none with one task); IQM over the seeds every task has, with a 95 % stratified "
        "bootstrap CI over those seeds (none with one seed). "
        + produced_by(dom, sorted(sources))
        + "".join(f" {s}: left out, {why}." for s, why in agg.get("missing", {}).items())
        + _skipped(agg.get("offline", {}).get("skipped", {}))
    )
    head = ("selection", "agent", "tasks", stat, "[25, 75]", "IQM", "IQM 95 % CI")
    return [Text(text), Table(head, tuple(rows))]


def _rank_corr(value: Any) -> str:
    """A Spearman correlation, or why there is none (one configuration: nothing to rank)."""
    if value is None or (isinstance(value, float) and value != value):
        return "- (one config)"
    return f"{value:.2f}"


def render_fqe(dom: Mapping[str, Any], domain: str, figures: Figures | None) -> list[Block]:
    rows = []
    for x in dom["fqe"]:
        true = x["true_returns"]
        texts = [
            f"{true[x['chosen']]:.1f}",
            f"{max(true.values()):.1f}",
            _rank_corr(x["spearman"]),
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
    text = (
        "Per-task episode return as the paper draws its control suite and locomotion figures: "
        "the online-selection tasks under online policy selection"
        + (
            f", the offline-selection tasks under naive offline selection ({_chosen_text(bars)})"
            if bars["offline"]
            else ""
        )
        + f"; bars mean {SPREAD} (the numbers are the tables' above; a bar of one seed is "
        "hatched, has no error bar and a 1 above it), diamonds the paper's (labelled with "
        "where they come from), dashed lines the dataset's 90th-percentile episode return. "
        "The figure's title says what produced the bars (where several settings did, each "
        "bar carries its letter)." + _skipped(bars["skipped"])
    )
    blocks: list[Block] = [Text(text)]
    p90 = dom.get("dataset_p90") or {}
    if any(_p90_text(dom, t) for t in p90):
        rows = [
            (
                Cell(row["task"], numeric=False),
                Cell(sel, numeric=False),
                Cell(_p90_text(dom, row["task"])),
            )
            for sel in ("online", "offline")
            for row in bars[sel]
        ]
        blocks.append(Table(("task", "selection", "dataset p90 return"), tuple(rows)))
    if figures is not None and (bars["online"] or bars["offline"]):
        path = figures.save(tasks_figure(dom, domain, figures.plt), f"{domain}_tasks")
        blocks.append(Image(path, f"{domain}: per-task scores"))
    return blocks


def _p90_text(dom: Mapping[str, Any], task: str) -> str:
    """A task's dataset 90th-percentile return, or why it has none."""
    value = (dom.get("dataset_p90") or {}).get(task)
    if value is not None:
        return f"{value:.1f}"
    used = len((dom.get("datasets") or {}).get(task, []))
    return f"none: its runs used {used} datasets" if used > 1 else ""


def _status(flags: Sequence[bool]) -> str:
    """``all``, ``some`` or ``none`` of the numbers beside the paper's are comparable."""
    n = sum(flags)
    return "all" if flags and n == len(flags) else "some" if n else "none"


def _pct(x: float | None) -> str:
    return "" if x is None else f"{x:.1f}"


def render_atari_median(
    dom: Mapping[str, Any], domain: str, figures: Figures | None
) -> list[Block]:
    panel = dom["atari_median"]
    entries = []  # (selection label, agent, its numbers)
    for h, label in (("online", "online (tuning games)"), ("offline", "naive offline (held-out)")):
        half = panel.get(h)
        for a in dom["agents"] if half is not None else ():
            if a in half["agents"]:
                entries.append((label, a, half, half["agents"][a]))
    with_paper = [
        e
        for *_, e in entries
        if e["paper_same_games"] is not None or e["paper_all_games"] is not None
    ]
    status = _status([e["comparable"] for e in with_paper])
    names = sorted({a for _, a, _, e in entries if e in with_paper})
    rows = []
    for label, a, half, e in entries:
        lo, hi = e["interval_25_75"]
        mark = comparable_label(e) if e in with_paper else ""
        texts = [
            f"{e['games']} of {half['of']}",
            f"{e['median']:.1f}",
            f"[{lo:.1f}, {hi:.1f}]",
            _pct(e["paper_same_games"]),
            _pct(e["paper_all_games"]),
        ]
        rows.append(
            (
                Cell(label, numeric=False),
                Cell(a + _tags(dom, e["provenance"]), numeric=False, note=mark),
                *(Cell(t) for t in texts),
            )
        )
    sources = sorted({i for *_, e in entries for i in e["provenance"]})
    text = (
        "The paper's Atari figure: median normalised score over games (%) with a bootstrapped "
        "[25, 75] interval, online policy selection on the tuning games and naive offline "
        "selection on the held-out games"
        + (
            f" (configuration chosen on the tuning games: {_chosen_text(panel['offline'])})"
            if "offline" in panel
            else ""
        )
        + f". A game missing from the sweep is left out. {produced_by(dom, sources)}"
        + f" Note: {panel['note']}."
        + (
            " Each row beside the paper's says (comparable) only when every condition of the "
            "paper's numbers holds for every game behind it, else which it misses."
            if with_paper
            else ""
        )
        + "".join(f" {h}: left out, {why}." for h, why in panel["missing"].items())
        + _skipped(panel.get("offline", {}).get("skipped", {}))
        + _small_denominators(dom, dom["tasks"])
    )
    paper = paper_head("paper's table, same games", dom, names, status)
    head = (
        "selection",
        "agent",
        "games",
        "median",
        "[25, 75]",
        paper,
        "paper's table, all games (the same settings)",
    )
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
    sources: set[int] = set()
    for a in agents:
        bars = [b for b in panel["agents"][a] if b["paper_improvement"] is not None]
        status = _status([b["comparable"] for b in bars])
        head += [a, paper_head(a, dom, [a], status)]
        sources.update(i for b in panel["agents"][a] for i in b["provenance"])
    rows = []
    for task in dom["tasks"]:
        if not any(task in by[a] for a in agents):
            continue
        mark = " †" if dom.get("reference_flags", {}).get(task) else ""
        cells = [Cell(task + mark, numeric=False), Cell(task_selection(task), numeric=False)]
        for a in agents:
            b = by[a].get(task)
            beside = b is not None and b["paper_improvement"] is not None
            ours = "" if b is None else f"{b['improvement']:+.1f}" + _tags(dom, b["provenance"])
            paper = f"{b['paper_improvement']:+.1f}" if beside else ""
            cells += [
                Cell(
                    ours,
                    bold=bool(b and b["improvement"] >= 0),
                    note=comparable_label(b) if beside else "",
                ),
                Cell(paper),
            ]
        rows.append(tuple(cells))
    text = (
        "The paper's appendix figure (Atari normalized performance): per game and agent, the "
        "normalised score improvement over the best behaviour snapshot (normalised score - 100, "
        "in %; 0: as good as the best snapshot, -100: random), each game under its own "
        "protocol; in bold an improvement. "
        + produced_by(dom, sorted(sources))
        + " Note: the paper prints this figure without numbers; 'paper' is its per-game "
        "appendix table normalised with the reference scores used here."
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
            (
                Cell(str(v["value"]), numeric=False),
                Cell(f"{v['games']} of {panel['of']}"),
                Cell(f"{v['median']:.1f}"),
                Cell(f"[{v['interval_25_75'][0]:.1f}, {v['interval_25_75'][1]:.1f}]"),
            )
            for v in panel["values"]
        )
        text = (
            f"{SENSITIVITY_TITLES[name]} (the paper's appendix ablation): median normalised "
            f"score (%) over the tuning games per value of {panel['field']}, each game's other "
            "hyper-parameters chosen by online policy selection, with a bootstrapped [25, 75] "
            f"interval. The paper draws this figure without numbers over the grid "
            f"{paper['grid']} and found {paper['best']} best. "
            + produced_by(dom, sorted({i for v in panel["values"] for i in v["provenance"]}))
        )
        head = (panel["field"], "games", "median", "[25, 75]")
        blocks: list[Block] = [Text(text), Table(head, rows)]
        if figures is not None:
            fig = sensitivity_figure(panel, SENSITIVITY_TITLES[name], figures.plt)
            blocks.append(Image(figures.save(fig, name), SENSITIVITY_TITLES[name]))
        return blocks

    return render_sensitivity


PROVENANCE_COLUMNS: tuple[tuple[str, Callable[[int, Mapping[str, Any]], str]], ...] = (
    ("", lambda i, p: _label(i)),
    ("preset", lambda i, p: str(p["preset"] or "unknown")),
    ("learner steps", lambda i, p: steps_text(p["steps"])),
    ("pre-training", lambda i, p: steps_text(p["pretrain_steps"]) if p["pretrain_steps"] else ""),
    ("data", lambda i, p: data_text(p["data"])),
    (
        "evaluation episodes",
        lambda i, p: "unknown" if p["eval_episodes"] is None else str(p["eval_episodes"]),
    ),
    ("agents", lambda i, p: ", ".join(p["agents"])),
    ("runs", lambda i, p: f"{p['runs']} ({_count(len(p['tasks']), 'task')})"),
    ("runs meeting the run conditions", lambda i, p: f"{p['comparable_runs']} of {p['runs']}"),
)
"""The table of what produced a domain's numbers: (heading, cell of entry i)."""

CONDITION_NAMES = {
    "preset": "preset",
    "budget": "budget",
    "data": "data",
    "episodes": "episodes (evaluation episodes per run)",
    "seeds": "seeds",
    "selection": "selection",
}


def render_provenance(dom: Mapping[str, Any], domain: str) -> list[Block]:
    """What produced the domain's numbers, first in its section: one row per distinct preset,
    learner budget, data and evaluation episodes of its runs (the letters its cells carry
    where there are several) and how many of those runs meet the paper's run conditions; then
    the conditions of the paper's numbers: what the paper states of each (cited), and what a
    comparable number of rlu's needs."""
    entries = dom.get("provenance", [])
    if not entries:
        return []
    rows = tuple(
        tuple(Cell(f(i, p), numeric=False) for _, f in PROVENANCE_COLUMNS)
        for i, p in enumerate(entries)
    )
    runs = sum(p["runs"] for p in entries)
    comparable = sum(p["comparable_runs"] for p in entries)
    if comparable == runs:
        verdict = (
            "Every run here meets the run conditions (preset, budget, data, evaluation "
            "episodes); each cell still says whether its seeds and its selection do."
        )
    elif comparable == 0:
        verdict = (
            "No run here meets them: the paper's numbers are shown beside rlu's as a reference, "
            "every column of them is headed not comparable, and each cell says which "
            "conditions it misses."
        )
    else:
        verdict = (
            f"{comparable} of {runs} runs here meet the run conditions (preset, budget, data, "
            "evaluation episodes): the paper's numbers are a comparison only beside the cells "
            "labelled (comparable); the others say which conditions they miss."
        )
    states = dom.get("paper_states") or {}
    if not states.get("table"):  # no numbers of the paper's to compare with
        intro = (
            "What produced these numbers: every run's preset, learner steps (pre-training "
            "apart), data and evaluation episodes"
            + (
                ", one letter per combination, the letter each number below carries"
                if len(entries) > 1
                else ""
            )
            + ". The paper reports no numbers for these tasks."
        )
        return [Text(intro), Table(tuple(h for h, _ in PROVENANCE_COLUMNS), rows)]
    intro = (
        "What produced these numbers: every run's preset, learner steps (pre-training apart), "
        "data and evaluation episodes"
        + (
            ", one letter per combination, the letter each number below carries"
            if len(entries) > 1
            else ""
        )
        + ". A number of rlu's compares with the paper's only when every condition of the "
        "paper's number holds, each recorded by the runs and checked here (the table below: "
        "what the paper states, cited, and what rlu's number needs; where the paper states "
        "nothing, rlu's choice stands in and is named as rlu's"
        + (f": {'; '.join(states['stand_ins'])}" if states.get("stand_ins") else "")
        + "). "
        + verdict
    )
    blocks: list[Block] = [Text(intro), Table(tuple(h for h, _ in PROVENANCE_COLUMNS), rows)]
    if states.get("needs"):
        cond_rows = []
        for c, name in CONDITION_NAMES.items():
            st = states[c]
            said = "nothing" if st["paper"] is None else _said(st["paper"])
            cond_rows.append(
                (
                    Cell(name, numeric=False),
                    Cell(said, numeric=False),
                    Cell(st["where"], numeric=False),
                    Cell(states["needs"][c], numeric=False),
                )
            )
        head = ("condition", "the paper states", "where", "a comparable number of rlu's needs")
        blocks.append(Table(head, tuple(cond_rows)))
    return blocks


def _said(value: Any) -> str:
    return f"{steps_text(value)} steps" if isinstance(value, int) else str(value)


def render_curves(dom: Mapping[str, Any], domain: str, figures: Figures | None) -> list[Block]:
    panel = dom["curves"]
    rows = []
    for t in panel["tasks"]:
        for a, c in t["agents"].items():
            last = (
                _fmt(c["mean"][-1], None if c["std"] is None else c["std"][-1])
                if c["steps"]
                else ""
            )
            rows.append(
                (
                    Cell(t["task"], numeric=False),
                    Cell(a, numeric=False),
                    Cell(c["config"], numeric=False),
                    Cell(c["protocol"], numeric=False),
                    Cell(str(c["n_seeds"])),
                    Cell(str(len(c["steps"]))),
                    Cell(steps_text(c["steps"][-1]) if c["steps"] else ""),
                    Cell(last),
                )
            )
    text = (
        "Learning curves: evaluation return against learner steps, from each run's eval.jsonl, "
        "of the configuration each task's protocol chose (the tables'). Per agent, every seed "
        f"as a thin line and their mean as a thick one with a band of {SPREAD}, at the steps "
        "every seed evaluated (no band with one seed)."
        + (
            f" Without evaluations on record: {', '.join(panel['without_curve'])}."
            if panel["without_curve"]
            else ""
        )
    )
    head = (
        "task",
        "agent",
        "configuration",
        "chosen by",
        "seeds",
        "evaluations",
        "last step",
        f"last mean {SPREAD}",
    )
    blocks: list[Block] = [Text(text), Table(head, tuple(rows))]
    if figures is not None:
        path = figures.save(curves_figure(dom, domain, figures.plt), f"{domain}_curves")
        blocks.append(Image(path, f"{domain}: learning curves"))
    return blocks


def render_profiles(dom: Mapping[str, Any], domain: str, figures: Figures | None) -> list[Block]:
    splits = dom["profiles"]["splits"]
    rows = []
    for split, half in splits.items():
        tau = np.asarray(half["tau"])
        mid = int(np.argmin(np.abs(tau - np.median(tau))))
        for a, e in half["agents"].items():
            ci = "" if e["ci"] is None else f"[{e['ci'][0][mid]:.2f}, {e['ci'][1][mid]:.2f}]"
            rows.append(
                (
                    Cell(PROFILE_SPLITS[split], numeric=False),
                    Cell(a, numeric=False),
                    Cell(str(len(half["tasks"]))),
                    Cell(str(len(e["seeds"]))),
                    Cell(f"{tau[mid]:.1f}"),
                    Cell(f"{e['fraction'][mid]:.2f}"),
                    Cell(ci),
                )
            )
    score = "normalised scores" if dom["normalised"] else "returns"
    text = (
        f"Performance profiles (rliable's, on {score}): per split under its own protocol, the "
        "fraction of an agent's (seed, task) runs scoring above tau, over the tasks every agent "
        "of the split has and the seeds all of them have; 95 % stratified bootstrap confidence "
        "intervals over seeds (tasks as strata; none with one seed). The table reads each "
        "profile at the middle tau. " + produced_by(dom, _rliable_sources(splits))
    )
    head = ("selection", "agent", "tasks", "seeds", "tau", "fraction > tau", "95 % CI")
    blocks: list[Block] = [Text(text), Table(head, tuple(rows))]
    if figures is not None:
        path = figures.save(profiles_figure(dom, figures.plt), f"{domain}_profiles")
        blocks.append(Image(path, f"{domain}: performance profiles"))
    return blocks


def _rliable_sources(splits: Mapping[str, Any]) -> list[int]:
    return sorted({i for h in splits.values() for i in h["provenance"]})


def render_improvement(dom: Mapping[str, Any], domain: str, figures: Figures | None) -> list[Block]:
    splits = dom["improvement"]["splits"]
    rows = []
    for split, half in splits.items():
        for pr in half["pairs"]:
            ci = "" if pr["ci"] is None else f"[{pr['ci'][0]:.2f}, {pr['ci'][1]:.2f}]"
            rows.append(
                (
                    Cell(PROFILE_SPLITS[split], numeric=False),
                    Cell(f"P({pr['x']} > {pr['y']})", numeric=False),
                    Cell(str(len(half["tasks"]))),
                    Cell(f"{pr['seeds'][0]} / {pr['seeds'][1]}"),
                    Cell(f"{pr['probability']:.2f}"),
                    Cell(ci),
                )
            )
    text = (
        "Probability of improvement (rliable's): P(X > Y), the chance that a run of X on a "
        "task scores above a run of Y (ties count half; Mann-Whitney), averaged over the tasks "
        "both have, X ranked above Y by the IQM of its runs; 95 % stratified bootstrap "
        "confidence intervals over seeds (none where both agents have one seed). "
        + produced_by(dom, _rliable_sources(splits))
    )
    head = ("selection", "pair", "tasks", "seeds X / Y", "P(X > Y)", "95 % CI")
    blocks: list[Block] = [Text(text), Table(head, tuple(rows))]
    if figures is not None:
        path = figures.save(improvement_figure(dom, figures.plt), f"{domain}_improvement")
        blocks.append(Image(path, f"{domain}: probability of improvement"))
    return blocks


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
    "curves": render_curves,
    "profiles": render_profiles,
    "improvement": render_improvement,
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
    "curves": "Learning curves",
    "profiles": "Performance profiles",
    "improvement": "Probability of improvement",
}
"""Each panel's name in the line that says why it is left out."""


def sections(report: Mapping[str, Any], figures: Figures | None) -> list[Section]:
    out = []
    for domain, dom in report["domains"].items():
        blocks: list[Block] = render_provenance(dom, domain)
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
