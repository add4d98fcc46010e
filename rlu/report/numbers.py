"""The numbers of ``rlu report``: the runs' result records in, one JSON-serialisable dict out.

Pure: no files written, nothing drawn (``rlu.report.render`` turns this dict into
Markdown, HTML and PNG). Per domain, the report holds the domain's ``agents`` and ``tasks``, the
``provenance`` of its runs and one entry per *panel*.

``provenance`` lists every distinct (preset, learner steps, pre-training steps, evaluation
episodes, data) of the domain's runs (``run_provenance``); every cell, aggregate and bar names
the entries of the runs behind it (indices into that list) and carries ``conditions``: for
each condition of the paper's numbers (``rlu.report.conditions``: preset, budget,
data, evaluation episodes, seeds, selection) None where it holds, else why not; ``missing``
names the ones that do not hold and ``comparable`` is true only when none is missing. What the
report checks of each agent's paper preset comes from the caller (``paper``, ``(agent,
discrete) -> PaperPreset``: this package may not import the agents); without it no cell is
comparable. The paper's numbers stay beside every cell, and the renderer heads them as a
comparison only where the cells are comparable.

Spreads are one kind everywhere: the sample standard deviation over seeds (ddof 1, ``std``),
None for a cell of one seed (it has no spread, and is shown as one seed); intervals are named
where they stand (bootstrapped percentile intervals, stratified bootstrap confidence intervals).

Each split follows its own protocol (the paper's §2.2 and §4), never mixed:

- ``online``: the online-selection tasks, task x agent, mean ± sample std over seeds of the
  final evaluation score of the configuration chosen by online policy selection (best per
  task), ``bold`` on the best mean of a row and on every mean ± std that overlaps it (the
  paper's convention), and per row the paper's number of every agent it has one for, whether
  rlu has that cell or not (``paper``; ``rlu/resources/paper_results.json``, a copy of the
  appendix tables of Gulcehre et al. 2020);
- ``offline_naive``: the offline-selection tasks under the paper's naive offline policy selection
  (per agent the configuration with the best mean, median for Atari, over the domain's online
  tasks, applied unchanged to the offline ones; an agent that ran one configuration needs no
  selection);
- ``aggregates``: per split and agent, the mean (median for Atari, on normalised scores) over the
  split's tasks under the split's protocol, with a bootstrapped [25, 75] percentile interval, and
  the IQM with a 95 % stratified bootstrap confidence interval over seeds (Agarwal et al. 2021,
  rliable);
- ``fqe``: offline policy selection by FQE estimates, when ``fqe.json`` is given;
- ``dataset_p90``: each task's dataset 90th-percentile episode return, when datasets are named;
- ``task_bars`` (every domain but Atari; the paper's control suite and locomotion figures): per
  task, the agents' scores under the task's own protocol (drawn with the ``dataset_p90`` line);
- ``atari_median`` (the paper's Atari figure, two panels): the median normalised score with a
  bootstrapped [25, 75] interval, online policy selection on the tuning games and naive offline
  selection on the held-out games the sweep covers;
- ``atari_per_game`` (the paper's appendix figure "Atari normalized performance"): per game and
  agent, the normalised score improvement over the best behaviour snapshot (normalised - 100);
- ``iqn_tau`` and ``bcq_threshold`` (the paper's appendix ablations): per value of IQN's
  ``num_tau_samples`` and discrete BCQ's ``threshold``, the median normalised score over the
  tuning games, each game's other hyper-parameters chosen online;
- ``curves`` (``rlu.report.curves``): per task and agent, evaluation return against
  learner steps of the configuration the task's protocol chose, every seed's curve and their
  mean ± sample std at the steps every seed evaluated (from each run's eval.jsonl, given as
  each record's ``curve``);
- ``profiles`` and ``improvement`` (``rlu.report.profiles``: rliable's numbers,
  computed vectorised): per split under its protocol, each agent's performance profile (the
  fraction of its runs scoring above tau) and the probability of improvement of one agent over
  another, both over the tasks every agent of the split has, with 95 % stratified bootstrap
  confidence intervals over seeds.

Beside the Atari panels stand the paper's per-game table normalised with the same reference
scores (the paper prints those figures without numbers; its table is the nearest number).

Adding a panel is one function here, ``panel(ctx: DomainContext) -> dict | Absent | None``
registered in ``PANELS``, plus one renderer registered under the same name in
``rlu.report.render.RENDERERS``. None: the panel does not apply to this domain;
``Absent(reason)``: it applies but the sweep holds no data for it (the report says why in one
line, ``dom["absent"]``).

Task metadata (domain, selection split) comes from ``rlu.tasks``; a task id that is not in the
registry is reported under the domain ``other`` as an online-selection task.
"""

from __future__ import annotations

import itertools
import json
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import numpy as np

from rlu.domains import DOMAINS
from rlu.domains.paper import TASK_FIGURES
from rlu.evaluation.protocols import Selection, offline_selection_naive, online_selection
from rlu.evaluation.reference import denominator_flags, random_spread
from rlu.evaluation.scores import (
    domain_statistic,
    load_reference_scores,
    normalized_score,
    stratified_bootstrap_ci,
    task_bootstrap_interval,
)
from rlu.report import conditions as cond
from rlu.report.conditions import PaperPreset
from rlu.types import RluError

# the paper's spelling of task names that differ from ours beyond case and spaces
_PAPER_ALIASES = {"rodenttwotouch": "rodenttwotap"}


def _key(name: str) -> str:
    k = name.lower().replace(" ", "").replace("_", "")
    return _PAPER_ALIASES.get(k, k)


CHALLENGE_MARK = ":"
"""An RWRL result under a challenge other than ``none`` is reported under ``<task id>:<challenge>``
(``rwrl/walker_walk:easy``), apart from the same task's ``none`` results, as the paper's RWRL
results are."""


def report_key(record: Mapping[str, Any]) -> str:
    """The task a result is reported under: its task id, with the RWRL challenge it was
    evaluated in when that is not ``none``."""
    challenge = record.get("env_settings", {}).get("challenge", "none")
    return record["task"] if challenge == "none" else f"{record['task']}{CHALLENGE_MARK}{challenge}"


def task_info(task_id: str) -> tuple[str, str, str]:
    """(domain, selection, display name) of a task id (or of a ``report_key``)."""
    from rlu.tasks import get_task

    base, _, challenge = task_id.partition(CHALLENGE_MARK)
    try:
        t = get_task(base)
    except RluError:
        return "other", "online", task_id
    if t.id != base:  # a bare name that get_task resolved; report it under its own id
        return "other", "online", task_id
    return t.domain, t.selection, t.name + (f" ({challenge} challenge)" if challenge else "")


def load_paper_results() -> dict[str, Any]:
    """The paper's numbers shipped with rlu (``rlu/resources/paper_results.json``): per task and
    agent the mean, std and whether the paper bolds it."""
    return json.loads(resources.files("rlu.resources").joinpath("paper_results.json").read_text())


def paper_entry(
    task_id: str, agent: str, paper: Mapping[str, Any] | None = None
) -> dict[str, Any] | None:
    """The paper's ``{mean, std, bold}`` for a task and agent, or None where the paper has none."""
    cols = {k.lower(): v for k, v in paper_row(task_id, paper).items()}
    return cols.get(agent.split(".")[-1].lower())


def paper_row(task_id: str, paper: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The paper's ``{agent: {mean, std, bold}}`` for a task, agents as the paper names them in
    its table's order; empty where the paper has no row for the task."""
    paper = load_paper_results() if paper is None else paper
    domain, _, name = task_info(task_id)
    table = paper.get(domain)
    if not isinstance(table, Mapping):
        return {}
    rows = {_key(k): v for k, v in table.items()}
    return dict(rows.get(_key(name)) or {})


def dataset_percentile(dataset: str, q: float = 90.0) -> float | None:
    """The ``q``-th percentile of a dataset's episode returns (None if it has no whole episode)."""
    from rlu.data import open_dataset

    returns = open_dataset(dataset).episode_returns()
    return float(np.percentile(returns, q)) if len(returns) else None


# The paper's sensitivity figures (appendix "Atari IQN Ablation Study" and "Atari BCQ Ablation
# Study", with the grids of the baselines appendix): the grid each figure spans and the value the
# paper found best by online policy selection. The figures print no numbers.
PAPER_SENSITIVITY: dict[str, dict[str, Any]] = {
    "iqn_tau": {"agent": "iqn", "field": "num_tau_samples", "grid": [8, 16, 32], "best": 16},
    "bcq_threshold": {
        "agent": "bcq",
        "field": "threshold",
        "grid": [0.25, 0.5, 0.75, 1.0],
        "best": 0.5,
    },
}

PAPER_FIGURE_ONLY = (
    'the paper prints this figure without numbers; the "paper\'s table" columns hold the median '
    "of the paper's per-game appendix table (raw scores) normalised with the reference scores "
    "used here, which are not the paper's own (rlu/resources/atari_best_behaviour.json says where "
    "they come from)"
)


# --- what produced a number -----------------------------------------------------------------
DATA_SOURCES = ("release", "generated", "imported", "synthetic", "unknown")
"""A run record's ``data.source``: the release's own files, data ``rlu generate`` made, data
imported from another format, synthetic test data, or a record from before runs recorded it."""

PaperPresets = Callable[[str, bool], "PaperPreset | None"]
"""``(agent, discrete) -> what the report checks of the agent's paper preset`` (None: unknown;
``rlu.report.conditions.paper_preset``)."""


def run_provenance(record: Mapping[str, Any]) -> dict[str, Any]:
    """What produced one run's score: its preset, learner steps (pre-training excluded),
    pre-training steps, evaluation episodes and data (``{"source": ..., ...}``, as the sweep
    recorded it). A field an older sweep did not record is None (data: source ``unknown``); the
    evaluation episodes of such a run are its final evaluation's returns, where it kept them."""
    data = record.get("data")
    if data is None:
        data = {"source": "unknown"}
    if not isinstance(data, Mapping) or data.get("source") not in DATA_SOURCES:
        got = data.get("source") if isinstance(data, Mapping) else data
        raise RluError(
            f"run {record.get('run')}: field data.source is {got!r}, not one of "
            f"{', '.join(DATA_SOURCES)}; rerun the sweep to rewrite its results.jsonl"
        )
    episodes = record.get("eval_episodes")
    if episodes is None and record.get("returns") is not None:
        episodes = len(record["returns"])
    return {
        "preset": record.get("preset"),
        "steps": record.get("steps"),
        "pretrain_steps": record.get("pretrain_steps"),
        "eval_episodes": episodes,
        "data": {k: data[k] for k in sorted(data)},
    }


def sample_std(scores: Sequence[float]) -> float | None:
    """The sample standard deviation (ddof 1) of scores over seeds; None for one score (no
    spread to show: a cell of one seed is shown as one seed)."""
    return float(np.std(scores, ddof=1)) if len(scores) > 1 else None


# --- the numbers ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Absent:
    """A panel that applies to the domain but has no data in the sweep: why, in one line."""

    reason: str


Normaliser = Callable[[str, float], float]


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
    datasets: Mapping[str, str | Sequence[str]]
    """Per task, the dataset (or datasets) its runs trained on."""
    fqe: Mapping[str, Any] | None
    reps: int
    normalise: Normaliser | None = None
    """Atari: ``(task id, raw score) -> normalised score`` for any game with reference scores
    (the paper's numbers are normalised with it too); None where the domain is not normalised."""
    provenance: tuple[Mapping[str, Any], ...] = ()
    """Every distinct ``run_provenance`` of the domain's runs."""
    run_provenance: Mapping[tuple[str, str, str, int], int] = field(default_factory=dict)
    """(task, agent, config, seed) -> index of the run's entry in ``provenance``."""
    presets: Mapping[str, PaperPreset | None] = field(default_factory=dict)
    """Per agent, what the report checks of its paper preset (None: unknown)."""
    run_conditions: Mapping[tuple[str, str, str, int], Mapping[str, str | None]] = field(
        default_factory=dict
    )
    """(task, agent, config, seed) -> the run conditions it meets (None) or misses (why)."""

    def sources(self, s: Selection) -> list[int]:
        """The ``provenance`` entries of a selection's runs."""
        return sorted({self.run_provenance[(s.task, s.agent, s.config, x)] for x in s.seeds})

    def conditions(self, s: Selection, protocol: str) -> dict[str, str | None]:
        """Every condition of the paper's number for a cell (``conditions.CONDITIONS``), None
        where it holds: its runs', its seeds and its selection's (``protocol``: ``online``,
        ``naive``, or ``only`` for an agent that ran one configuration)."""
        runs = [self.run_conditions[(s.task, s.agent, s.config, x)] for x in s.seeds]
        out = cond.merge(runs)
        out["seeds"] = cond.at_least(len(s.seeds), "seeds", self.domain)
        out["selection"] = self.selection_condition(s, protocol)
        return out

    def selection_condition(self, s: Selection, protocol: str) -> str | None:
        """Whether the protocol that chose a cell's configuration had comparable inputs (the
        runs it chose among, besides the cell's own, which the run conditions judge): online
        selection, comparable runs of every configuration of the paper's grid on the task;
        naive offline selection, the same on every online-selection task of the domain; an
        agent that ran one configuration, the paper's grid of one configuration."""
        preset = self.presets.get(s.agent)
        if protocol == "online":
            tasks: Sequence[str] = (s.task,)
        elif protocol == "naive":
            tasks = self.online_tasks
        else:
            tasks = (s.task,)
        recs = [r for r in self.records if r["agent"] == s.agent and r["task"] in tasks]
        why = []
        if protocol == "naive":
            every = _registry(self.domain, "online") or list(self.online_tasks)
            if len(self.online_tasks) < len(every):
                why.append(
                    f"chosen on {len(self.online_tasks)} of the domain's {len(every)} "
                    "online-selection tasks"
                )
        # the cell's own runs are judged by the run conditions; the selection by the others
        others = [r for r in recs if (r["task"], r["config"]) != (s.task, s.config)]
        bad = _not_comparable_inputs(self, others)
        if bad:
            why.append(f"chosen among runs that are not comparable ({bad})")
        grid = _grid_combinations(preset)
        if len(grid) > 1:
            for task in tasks:
                ran = [dict(r.get("overrides") or {}) for r in recs if r["task"] == task]
                seen = sum(any(o == g for o in ran) for g in grid)
                if seen < len(grid):
                    short = task.split("/", 1)[-1]
                    why.append(f"{seen} of the paper grid's {len(grid)} configurations on {short}")
        return "; ".join(why) or None


def _not_comparable_inputs(ctx: DomainContext, recs: Sequence[Mapping[str, Any]]) -> str:
    """The conditions the runs of a selection's inputs miss (their runs' and each
    configuration's seeds), as names; empty when every input is comparable."""
    names: list[str] = []
    per_config: dict[tuple[str, str], int] = defaultdict(int)
    for r in recs:
        key = (r["task"], r["agent"], r["config"], int(r["seed"]))
        names += [c for c in cond.RUN_CONDITIONS if ctx.run_conditions[key].get(c)]
        per_config[(r["task"], r["config"])] += 1
    if any(cond.at_least(n, "seeds", ctx.domain) for n in per_config.values()):
        names.append("seeds")
    return ", ".join(c for c in cond.CONDITIONS if c in names)


def _grid_combinations(preset: PaperPreset | None) -> list[dict[str, Any]]:
    """Every configuration of an agent's paper grid (one, the preset itself, without one)."""
    if preset is None or not preset.grid:
        return [{}]
    keys = sorted(preset.grid)
    return [
        dict(zip(keys, v, strict=True)) for v in itertools.product(*(preset.grid[k] for k in keys))
    ]


def online_panel(ctx: DomainContext) -> dict[str, Any] | Absent:
    if not ctx.online_tasks:
        return Absent(
            "the sweep has no online-selection task of this domain (its offline-selection tasks "
            "are under naive offline selection, never the per-task best configuration)"
        )
    return _table(ctx, _online(ctx, ctx.records), ctx.online_tasks, _ONLINE)


def offline_naive_panel(ctx: DomainContext) -> dict[str, Any] | Absent | None:
    if not ctx.offline_tasks:
        return None
    naive = _naive(ctx, ctx.records)
    if not naive.chosen:
        return Absent("; ".join(naive.skipped.values()))
    return {**naive.chosen_json(), **_table(ctx, naive.sel, ctx.offline_tasks, naive.protocol)}


def aggregates_panel(ctx: DomainContext) -> dict[str, Any] | Absent:
    """Per split, its protocol's aggregate over its tasks: online policy selection over the
    online-selection tasks, naive offline selection over the offline-selection tasks."""
    if _normalises(ctx.domain) and not ctx.normalised:
        return Absent(_NO_REFERENCE)  # Atari aggregates are over normalised scores only
    out: dict[str, Any] = {"statistic": domain_statistic(ctx.domain), "missing": {}}
    if ctx.online_tasks:
        out["online"] = _aggregates(ctx, _online(ctx, ctx.scored), ctx.online_tasks, _ONLINE)
    if ctx.offline_tasks:
        naive = _naive(ctx, ctx.scored)
        if naive.chosen:
            out["offline"] = {
                **_aggregates(ctx, naive.sel, ctx.offline_tasks, naive.protocol),
                **naive.chosen_json(),
            }
        else:
            out["missing"]["offline"] = "; ".join(naive.skipped.values())
    if "online" not in out and "offline" not in out:
        return Absent("; ".join(out["missing"].values()))
    return out


def fqe_panel(ctx: DomainContext) -> list[dict[str, Any]] | None:
    if not ctx.fqe:
        return None
    return [x for x in ctx.fqe.get("selections", []) if x["task"] in ctx.tasks]


def dataset_p90_panel(ctx: DomainContext) -> dict[str, float | None] | None:
    """Each task's dataset 90th-percentile episode return; None for a task whose runs
    trained on several datasets (``datasets`` in the domain says which: no one line is the
    data's)."""
    if not ctx.datasets:
        return None
    out: dict[str, float | None] = {}
    for t in ctx.tasks:
        if t in ctx.datasets:
            paths = _paths(ctx.datasets[t])
            out[t] = dataset_percentile(paths[0]) if len(paths) == 1 else None
    return out


def _paths(value: str | Sequence[str]) -> list[str]:
    return [value] if isinstance(value, str) else list(value)


def task_bars_panel(ctx: DomainContext) -> dict[str, Any] | None:
    """The paper's control suite and locomotion figures: each task under its own protocol."""
    if not _draws(ctx.domain, "task_bars"):
        return None  # the paper draws Atari normalised: atari_median and atari_per_game
    online = _table(ctx, _online(ctx, ctx.records), ctx.online_tasks, _ONLINE)["rows"]
    naive = _naive(ctx, ctx.records)
    offline = _table(ctx, naive.sel, ctx.offline_tasks, naive.protocol)["rows"]
    return {"online": online, "offline": offline if naive.chosen else [], **naive.chosen_json()}


def atari_median_panel(ctx: DomainContext) -> dict[str, Any] | Absent | None:
    """The paper's Atari figure: median normalised score, [25, 75] bootstrap interval, online
    policy selection on the tuning games (left) and naive offline selection on the held-out
    games (right); each half covers the games the sweep has."""
    if not _draws(ctx.domain, "atari_median"):
        return None
    if ctx.normalise is None:
        return Absent(_NO_REFERENCE)
    out: dict[str, Any] = {"statistic": "median", "note": PAPER_FIGURE_ONLY, "missing": {}}
    all_online = _registry(ctx.domain, "online")
    all_offline = _registry(ctx.domain, "offline")
    if ctx.online_tasks:
        sel = online_selection(r for r in ctx.scored if r["task"] in ctx.online_tasks)
        out["online"] = _median_half(ctx, sel, ctx.online_tasks, all_online, {}, _ONLINE)
    else:
        out["missing"]["online"] = "the sweep has none of the 9 tuning games"
    if ctx.offline_tasks:
        naive = _naive(ctx, ctx.scored)
        if naive.chosen:
            half = _median_half(
                ctx, naive.sel, ctx.offline_tasks, all_offline, naive.skipped, naive.protocol
            )
            out["offline"] = {**half, **naive.chosen_json()}
        else:
            out["missing"]["offline"] = "; ".join(naive.skipped.values())
    else:
        out["missing"]["offline"] = "the sweep has none of the 37 held-out games"
    if "online" not in out and "offline" not in out:
        return Absent("; ".join(out["missing"].values()))
    return out


def atari_per_game_panel(ctx: DomainContext) -> dict[str, Any] | Absent | None:
    """The paper's appendix figure "Atari normalized performance": per agent and game, the
    normalised score improvement over the best behaviour snapshot, ``normalised - 100`` (0: as
    good as the best snapshot of the online DQN that logged the data), each game under its own
    protocol (online selection on tuning games, naive offline selection on held-out ones)."""
    if not _draws(ctx.domain, "atari_per_game"):
        return None
    if ctx.normalise is None:
        return Absent(_NO_REFERENCE)
    online = _online(ctx, ctx.scored)
    naive = _naive(ctx, ctx.scored)
    offline, skipped = naive.sel, naive.skipped
    agents: dict[str, list[dict[str, Any]]] = {}
    for agent in ctx.agents:
        bars = []
        for task in ctx.tasks:
            s = (online if task in ctx.online_tasks else offline).get((task, agent))
            if s is None:
                continue
            paper = _paper_normalised(ctx, task, agent)
            bars.append(
                {
                    "task": task,
                    "selection": task_info(task)[1],
                    "config": s.config,
                    "normalised": s.mean,
                    "improvement": s.mean - 100.0,
                    "paper_improvement": None if paper is None else paper - 100.0,
                    **_sourced(ctx, s, _ONLINE if task in ctx.online_tasks else naive.protocol),
                }
            )
        if bars:
            agents[agent] = sorted(bars, key=lambda b: -b["improvement"])
    if not agents:
        return Absent("; ".join(skipped.values()) or "no game has a result")
    return {"agents": agents, "skipped": skipped, "note": PAPER_FIGURE_ONLY}


def curves_panel(ctx: DomainContext) -> dict[str, Any] | Absent:
    """Learning curves of the configurations the tables show (``rlu.report.curves``)."""
    from rlu.report.curves import NO_CURVES, curves

    chosen = {k: (s.config, "online") for k, s in _online(ctx, ctx.records).items()}
    naive = _naive(ctx, ctx.records)
    chosen.update({k: (s.config, naive.protocol(k[1])) for k, s in naive.sel.items()})
    panel = curves(ctx.records, ctx.tasks, ctx.agents, chosen)
    return Absent(NO_CURVES) if panel is None else panel


def _split_selections(
    ctx: DomainContext,
) -> dict[str, tuple[dict[tuple[str, str], Selection], Protocol]]:
    """Per split, its protocol's selections on the scores the aggregates use, and how each
    agent's configuration was chosen."""
    out: dict[str, tuple[dict[tuple[str, str], Selection], Protocol]] = {}
    if ctx.online_tasks:
        out["online"] = (_online(ctx, ctx.scored), _ONLINE)
    naive = _naive(ctx, ctx.scored)
    if ctx.offline_tasks and naive.chosen:
        out["offline"] = (naive.sel, naive.protocol)
    return out


def _rliable_panel(ctx: DomainContext, which: str) -> dict[str, Any] | Absent | None:
    from rlu.report import profiles

    if _normalises(ctx.domain) and not ctx.normalised:
        return Absent(_NO_REFERENCE)
    splits = _split_selections(ctx)
    tasks = {"online": ctx.online_tasks, "offline": ctx.offline_tasks}
    mats = profiles.matrices({k: sel for k, (sel, _) in splits.items()}, tasks, ctx.agents)
    if which == "improvement":
        out = profiles.improvement(mats, ctx.reps)
        if not out:
            return Absent(
                "the probability of improvement compares two agents on the same "
                "tasks, and no split has two"
            )
    else:
        out = profiles.profiles(mats, ctx.reps)
        if not out:
            return Absent("no split has a task under its protocol")
    for split, half in out.items():
        sel, protocol = splits[split]
        cells = [_sourced(ctx, s, protocol) for (t, _), s in sel.items() if t in half["tasks"]]
        half.update(_merge_sourced(cells))
    return {"splits": out, "normalised": ctx.normalised}


def profiles_panel(ctx: DomainContext) -> dict[str, Any] | Absent | None:
    return _rliable_panel(ctx, "profiles")


def improvement_panel(ctx: DomainContext) -> dict[str, Any] | Absent | None:
    return _rliable_panel(ctx, "improvement")


def iqn_tau_panel(ctx: DomainContext) -> dict[str, Any] | Absent | None:
    return _sensitivity(ctx, "iqn_tau")


def bcq_threshold_panel(ctx: DomainContext) -> dict[str, Any] | Absent | None:
    return _sensitivity(ctx, "bcq_threshold")


Panel = Callable[[DomainContext], Any]
PANELS: dict[str, Panel] = {
    "online": online_panel,
    "offline_naive": offline_naive_panel,
    "aggregates": aggregates_panel,
    "fqe": fqe_panel,
    "dataset_p90": dataset_p90_panel,
    "task_bars": task_bars_panel,
    "atari_median": atari_median_panel,
    "atari_per_game": atari_per_game_panel,
    "iqn_tau": iqn_tau_panel,
    "bcq_threshold": bcq_threshold_panel,
    "curves": curves_panel,
    "profiles": profiles_panel,
    "improvement": improvement_panel,
}
"""Every panel of a domain, in report order (``rlu.report.render`` renders them)."""

_NO_REFERENCE = (
    "Atari scores are compared normalised, and a game of the sweep has no random or "
    "best-behaviour reference score (rlu/resources/random_scores.json, atari_best_behaviour.json)"
)
_NO_ONLINE_TASK = (
    "naive offline selection chooses a configuration on the online-selection tasks, and the "
    "sweep has none of this domain"
)


def _online(
    ctx: DomainContext, records: Sequence[Mapping[str, Any]]
) -> dict[tuple[str, str], Selection]:
    """Online policy selection over the online-selection tasks only."""
    return online_selection(r for r in records if r["task"] in ctx.online_tasks)


@dataclass(frozen=True)
class _Naive:
    """Naive offline selection over a domain's offline-selection tasks."""

    sel: dict[tuple[str, str], Selection]
    chosen: dict[str, str]
    """Per agent, the configuration chosen (on the online tasks, or the only one it ran)."""
    skipped: dict[str, str]
    """Per agent it cannot choose for, why."""
    only: list[str]
    """The agents that ran one configuration: nothing to select."""

    def protocol(self, agent: str) -> str:
        """How the configuration of an agent's cells was chosen: ``naive`` selection, or
        ``only`` (the agent ran one configuration: nothing to select)."""
        return "only" if agent in self.only else "naive"

    def chosen_json(self) -> dict[str, Any]:
        return {"chosen": self.chosen, "skipped": self.skipped, "only_configuration": self.only}


def _naive(ctx: DomainContext, records: Sequence[Mapping[str, Any]]) -> _Naive:
    """Naive offline selection over the offline-selection tasks of ``records`` (raw or
    normalised: the choice is made on ``ctx.scored`` either way)."""
    chosen, skipped, only = _naive_choices(ctx)
    picked = [
        r
        for r in records
        if r["task"] in ctx.offline_tasks and chosen.get(r["agent"]) == r["config"]
    ]
    return _Naive(online_selection(picked), chosen, skipped, only)


def _naive_choices(ctx: DomainContext) -> tuple[dict[str, str], dict[str, str], list[str]]:
    """Per agent that ran an offline-selection task, the configuration naive offline selection
    chooses (``{agent: config}``), ``{agent: why}`` for the agents it cannot choose for (no
    configuration run on every online task of the sweep), and the agents that ran one
    configuration in the domain: they need no selection, that configuration is the one."""
    chosen: dict[str, str] = {}
    skipped: dict[str, str] = {}
    only: list[str] = []
    if not ctx.offline_tasks:
        return chosen, skipped, only
    stat = domain_statistic(ctx.domain)
    for agent in ctx.agents:
        recs = [r for r in ctx.scored if r["agent"] == agent]
        if not any(r["task"] in ctx.offline_tasks for r in recs):
            continue
        configs = {r["config"] for r in recs}
        if len(configs) == 1:
            chosen[agent] = configs.pop()
            only.append(agent)
            continue
        if not ctx.online_tasks:
            skipped[agent] = (
                f"{_NO_ONLINE_TASK} (agent {agent!r} ran {len(configs)} configurations)"
            )
            continue
        try:
            pick, _ = offline_selection_naive(recs, ctx.online_tasks, ctx.offline_tasks, stat)
        except RluError as e:
            skipped[agent] = str(e)
            continue
        if agent not in pick:
            skipped[agent] = f"agent {agent!r} has no run on an online-selection task"
            continue
        chosen.update(pick)
    return chosen, skipped, only


Protocol = Callable[[str], str]
"""agent -> how its cells' configuration was chosen: ``online``, ``naive`` or ``only``."""


def _ONLINE(agent: str) -> str:
    return "online"


def _sourced(ctx: DomainContext, s: Selection, protocol: Protocol) -> dict[str, Any]:
    """A number's provenance entries and every condition of the paper's number it meets."""
    c = ctx.conditions(s, protocol(s.agent))
    gone = cond.missing(c)
    return {
        "provenance": ctx.sources(s),
        "conditions": c,
        "missing": gone,
        "comparable": not gone,
        "not_comparable": [c[k] for k in gone],
    }


def _merge_sourced(parts: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The provenance of a number computed from several (an aggregate over cells)."""
    c = cond.merge([p["conditions"] for p in parts])
    gone = cond.missing(c)
    return {
        "provenance": sorted({i for p in parts for i in p["provenance"]}),
        "conditions": c,
        "missing": gone,
        "comparable": bool(parts) and not gone,
        "not_comparable": [c[k] for k in gone],
    }


def _paper_normalised(ctx: DomainContext, task: str, agent: str) -> float | None:
    """The paper's table score of a game and agent, normalised like ours (None: no number, or
    no reference score for the game)."""
    entry = paper_entry(task, agent, ctx.paper)
    if entry is None or ctx.normalise is None:
        return None
    try:
        return float(ctx.normalise(task, entry["mean"]))
    except KeyError:
        return None


def _paper_median(ctx: DomainContext, agent: str, tasks: Sequence[str]) -> float | None:
    values = [_paper_normalised(ctx, t, agent) for t in tasks]
    known = [v for v in values if v is not None]
    if not values or len(known) < len(values):
        return None
    return float(np.median(known))


def _median_half(
    ctx: DomainContext,
    sel: Mapping[tuple[str, str], Selection],
    tasks: Sequence[str],
    all_tasks: Sequence[str],
    skipped: Mapping[str, str],
    protocol: Protocol,
) -> dict[str, Any]:
    """One half of the Atari figure: per agent the median over its games with the interval,
    the paper's table over the same games and over all the split's games."""
    agents: dict[str, Any] = {}
    for agent in ctx.agents:
        cells = {t: sel[(t, agent)] for t in tasks if (t, agent) in sel}
        if not cells:
            continue
        med, (lo, hi) = task_bootstrap_interval(
            [c.mean for c in cells.values()], "median", reps=ctx.reps
        )
        agents[agent] = {
            "median": med,
            "interval_25_75": [lo, hi],
            "games": len(cells),
            "configs": {t: c.config for t, c in cells.items()},
            "paper_same_games": _paper_median(ctx, agent, list(cells)),
            "paper_all_games": _paper_median(ctx, agent, all_tasks),
            "paper_budget": cond.budget_of(ctx.domain, ctx.presets.get(agent))[0],
            **_merge_sourced([_sourced(ctx, c, protocol) for c in cells.values()]),
        }
    return {
        "games": list(tasks),
        "of": len(all_tasks),
        "agents": agents,
        "skipped": dict(skipped),
    }


def _sensitivity(ctx: DomainContext, name: str) -> dict[str, Any] | Absent | None:
    """Median normalised score over the sweep's tuning games per value of one hyper-parameter
    of one agent; per game and value, the best setting of the other hyper-parameters (online
    policy selection, as the paper's ablations evaluate)."""
    if not _draws(ctx.domain, name):
        return None
    paper = PAPER_SENSITIVITY[name]
    agent, fld = paper["agent"], paper["field"]
    if agent not in ctx.agents:
        return Absent(f"the sweep has no {agent} runs")
    if ctx.normalise is None:
        return Absent(_NO_REFERENCE)
    if not ctx.online_tasks:
        return Absent(
            f"the paper's {agent} {fld} figure is over the tuning games (online policy "
            "selection) and the sweep has none of them"
        )
    by_value: dict[Any, list[Mapping[str, Any]]] = defaultdict(list)
    for r in ctx.scored:
        overrides = r.get("overrides") or {}
        if r["agent"] == agent and r["task"] in ctx.online_tasks and fld in overrides:
            by_value[overrides[fld]].append(r)
    if len(by_value) < 2:
        return Absent(
            f"the sweep's {agent} runs on tuning games set {len(by_value)} value(s) of {fld} "
            f"(a grid over {fld}, e.g. the paper's {paper['grid']}, draws the figure)"
        )
    values = []
    for value in sorted(by_value, key=_order):
        sel = online_selection(by_value[value])
        cells = {t: sel[(t, agent)] for t in ctx.online_tasks if (t, agent) in sel}
        med, (lo, hi) = task_bootstrap_interval(
            [c.mean for c in cells.values()], "median", reps=ctx.reps
        )
        values.append(
            {
                "value": value,
                "median": med,
                "interval_25_75": [lo, hi],
                "games": len(cells),
                "configs": {t: c.config for t, c in cells.items()},
                **_merge_sourced([_sourced(ctx, c, _ONLINE) for c in cells.values()]),
            }
        )
    return {
        "agent": agent,
        "field": fld,
        "games": list(ctx.online_tasks),
        "of": len(_registry(ctx.domain, "online")),
        "values": values,
        "paper": {"grid": paper["grid"], "best": paper["best"], "numbers": None},
    }


def _order(value: Any) -> tuple[int, Any]:
    # numbers in numeric order, anything else after them by its text
    if isinstance(value, int | float) and not isinstance(value, bool):
        return 0, float(value)
    return 1, str(value)


def _registry(domain: str, selection: str) -> list[str]:
    from rlu.tasks import list_tasks

    return [t.id for t in list_tasks(domain, selection)]


def _normalises(domain: str) -> bool:
    """Whether the domain's scores are compared normalised (its entry's ``normalised``; a domain
    of the report's own, ``other``: no)."""
    known = DOMAINS.get(domain)
    return known is not None and known.normalised


def _draws(domain: str, figure: str) -> bool:
    """Whether the report draws the paper's figure ``figure`` (a panel's name) for the domain:
    one of its entry's ``report_figures`` (a domain of the report's own, ``other``: the per-task
    bars)."""
    known = DOMAINS.get(domain)
    return figure in (known.report_figures if known is not None else TASK_FIGURES)


def build_report(
    records: Sequence[Mapping[str, Any]],
    datasets: Mapping[str, str | Sequence[str]] | None = None,
    random_scores: Mapping[str, float] | None = None,
    best_behaviour: Mapping[str, float] | None = None,
    reps: int = 2000,
    fqe: Mapping[str, Any] | None = None,
    paper: PaperPresets | None = None,
) -> dict[str, Any]:
    """Every number of the report (JSON-serialisable), from the runs' result records (a
    sweep's results.jsonl records, or ``rlu.training.runs.run_record`` of run folders; a record's
    ``curve`` is its evaluations, for the learning curves) and, if given, the FQE selections
    that ``rlu.training.restore.fqe_selection`` wrote. ``paper(agent, discrete)`` is what the report
    checks of an agent's paper preset (``PaperPreset``); without it no cell is comparable."""
    table = load_paper_results()
    by_domain: dict[str, list[Mapping[str, Any]]] = defaultdict(list)
    for r in records:
        if r.get("score") is None:
            raise RluError(f"run {r.get('run')} has no evaluation score; rerun it with evaluation")
        by_domain[task_info(r["task"])[0]].append(r)
    out: dict[str, Any] = {"domains": {}}
    for domain, recs in sorted(by_domain.items()):
        norm: Normaliser | None = None
        refs: dict[str, Any] | None = None
        if _normalises(domain):
            norm, refs = _normaliser(_task_order(recs), random_scores, best_behaviour)
        ctx = _context(domain, recs, norm, table, datasets, fqe, reps, paper)
        out["domains"][domain] = _domain_json(ctx, refs)
    return out


def _task_order(recs: Sequence[Mapping[str, Any]]) -> list[str]:
    """The records' tasks in the report's order: online-selection tasks first, then by id."""
    return sorted({r["task"] for r in recs}, key=lambda t: (task_info(t)[1] != "online", t))


def _context(
    domain: str,
    recs: Sequence[Mapping[str, Any]],
    norm: Normaliser | None,
    table: Mapping[str, Any],
    datasets: Mapping[str, str | Sequence[str]] | None,
    fqe: Mapping[str, Any] | None,
    reps: int,
    paper: PaperPresets | None,
) -> DomainContext:
    """What the panels read of one domain's records: the scores they compare (normalised by
    ``norm`` where the domain is), each run's data source and the paper's conditions it meets."""
    agents = sorted({r["agent"] for r in recs})
    tasks = _task_order(recs)
    # tables show raw returns (as the paper's appendix does); selection across tasks and the
    # aggregates use normalised scores for Atari
    scored = [
        {**r, "score": float(norm(r["task"], r["score"])) if norm else float(r["score"])}
        for r in recs
    ]
    sources: dict[str, int] = {}
    run_source: dict[tuple[str, str, str, int], int] = {}
    for r in sorted(recs, key=lambda r: json.dumps(run_provenance(r), sort_keys=True)):
        key = json.dumps(run_provenance(r), sort_keys=True)
        run_source[(r["task"], r["agent"], r["config"], int(r["seed"]))] = sources.setdefault(
            key, len(sources)
        )
    discrete = cond.paper_conditions(domain).discrete_agents
    presets = {a: None if paper is None else paper(a, discrete) for a in agents}
    conditions = {
        (r["task"], r["agent"], r["config"], int(r["seed"])): cond.run_conditions(
            run_provenance(r), _overrides(r), r["task"], domain, presets[r["agent"]]
        )
        for r in recs
    }
    return DomainContext(
        domain=domain,
        records=tuple(recs),
        scored=tuple(scored),
        agents=tuple(agents),
        tasks=tuple(tasks),
        online_tasks=tuple(t for t in tasks if task_info(t)[1] == "online"),
        offline_tasks=tuple(t for t in tasks if task_info(t)[1] == "offline"),
        normalised=norm is not None,
        paper=table,
        datasets=dict(datasets or {}),
        fqe=fqe,
        reps=reps,
        normalise=norm,
        provenance=tuple(json.loads(k) for k in sources),
        run_provenance=run_source,
        presets=presets,
        run_conditions=conditions,
    )


def _domain_json(ctx: DomainContext, refs: dict[str, Any] | None) -> dict[str, Any]:
    """One domain's part of the report: what it holds, its data sources, the paper's presets
    and statements, the reference scores (``refs``, where normalised) and every panel."""
    agents, tasks = list(ctx.agents), list(ctx.tasks)
    dom: dict[str, Any] = {"agents": agents, "tasks": tasks, "normalised": ctx.normalised}
    dom["datasets"] = {t: _paths(ctx.datasets[t]) for t in tasks if t in ctx.datasets}
    dom["provenance"] = _provenance_entries(ctx)
    dom["paper_presets"] = {a: _preset_json(ctx, a) for a in agents}
    dom["paper_states"] = _statements(ctx)
    if refs is not None:  # set with the normaliser
        dom["reference_scores"] = refs
        dom["reference_flags"] = denominator_flags(refs, random_spread())
    dom["panels"] = []
    dom["absent"] = {}
    for name, panel in PANELS.items():
        data = panel(ctx)
        if isinstance(data, Absent):
            dom["absent"][name] = data.reason
        elif data is not None:
            dom[name] = data
            dom["panels"].append(name)
    return dom


def _provenance_entries(ctx: DomainContext) -> list[dict[str, Any]]:
    """The domain's provenance entries, each with the runs behind it: how many, which agents and
    tasks, and how many of them are comparable with the paper's numbers."""
    out = []
    for i, p in enumerate(ctx.provenance):
        keys = [k for k, j in ctx.run_provenance.items() if j == i]
        agents = sorted({k[1] for k in keys})
        comparable = sum(not any(ctx.run_conditions[k].values()) for k in keys)
        tasks = sorted({k[0] for k in keys})
        out.append(
            {
                **p,
                "runs": len(keys),
                "agents": agents,
                "tasks": tasks,
                "comparable_runs": comparable,
            }
        )
    return out


def _overrides(record: Mapping[str, Any]) -> Mapping[str, Any] | None:
    """A record's overrides of its preset (None: not recorded; a ``default`` configuration
    has none)."""
    if record.get("overrides") is not None:
        return record["overrides"]
    return {} if record.get("config") == "default" else None


def _preset_json(ctx: DomainContext, agent: str) -> dict[str, Any]:
    """What the report knew of an agent's paper preset, and the budget its cells compare at
    (``stated``: the paper's own number; else rlu's)."""
    preset = ctx.presets.get(agent)
    budget, stated = cond.budget_of(ctx.domain, preset)
    return {
        "known": preset is not None,
        "steps": None if preset is None else preset.steps,
        "grid": {} if preset is None else {k: list(v) for k, v in preset.grid.items()},
        "budget": budget,
        "budget_stated": stated,
    }


def _statements(ctx: DomainContext) -> dict[str, Any]:
    """What the paper states of each condition for this domain, where, and rlu's stand-in."""
    fam = cond.paper_conditions(ctx.domain).statements
    out: dict[str, Any] = {
        k: {"paper": v.paper, "where": v.where, "rlu": v.rlu, "rlu_where": v.rlu_where}
        for k, v in fam.items()
    }
    out["table"] = cond.PAPER_TABLES.get(ctx.domain)
    steps = {a: p.steps for a, p in ctx.presets.items() if p is not None}
    out["stand_ins"] = cond.stand_ins(ctx.domain, steps)
    out["needs"] = cond.needs(ctx.domain, steps)
    return out


def _normaliser(
    tasks: Sequence[str],
    random_scores: Mapping[str, float] | None,
    best_behaviour: Mapping[str, float] | None,
) -> tuple[Normaliser, dict[str, Any]] | tuple[None, None]:
    """(score normaliser, the reference scores of ``tasks``) or (None, None) where a game of
    ``tasks`` lacks one.

    The references are the given ones or the shipped files (``rlu/resources``); a game without
    both leaves the domain unnormalised (there is no estimate from the sweep's data: a
    transition dataset's returns are clipped and span a whole run, not one snapshot). The
    normaliser takes any game with both references (KeyError for one without): the paper's
    numbers of games outside the sweep are normalised with it too."""
    if random_scores is None:
        try:
            random_scores = load_reference_scores("random_scores")
        except RluError:
            random_scores = {}
    if best_behaviour is None:
        best_behaviour = load_reference_scores("atari_best_behaviour")

    def ref(task: str) -> dict[str, Any] | None:
        # reference files key by task id (random_scores.json) or by game name
        found = []
        for table in (random_scores, best_behaviour):
            found += [next((table[k] for k in (task, task_info(task)[2]) if k in table), None)]
        rnd, best = found
        if rnd is None or best is None:
            return None
        return {"random": rnd, "best_behaviour": best, "best_behaviour_source": "given"}

    refs: dict[str, Any] = {}
    for t in tasks:
        refs[t] = ref(t)
        if refs[t] is None:
            return None, None

    def norm(task: str, score: float) -> float:
        r = refs.get(task) or ref(task)
        if r is None:
            raise KeyError(task)
        return float(normalized_score(score, r["random"], r["best_behaviour"]))

    return norm, refs


def _table(
    ctx: DomainContext,
    sel: Mapping[tuple[str, str], Selection],
    tasks: Sequence[str],
    protocol: Protocol,
) -> dict[str, Any]:
    rows = []
    for task in tasks:
        cells = {}
        for agent in ctx.agents:
            s = sel.get((task, agent))
            if s is None:
                continue
            cells[agent] = {
                "config": s.config,
                "mean": s.mean,
                "std": sample_std(s.scores),
                "seeds": list(s.seeds),
                "scores": list(s.scores),
                **_sourced(ctx, s, protocol),
            }
        # the paper's bold: the best mean, and every cell whose mean ± std overlaps the best's
        # (a cell of one seed has no spread: its mean alone)
        if cells:
            best = max(cells.values(), key=lambda c: c["mean"])
            for c in cells.values():
                c["bold"] = c["mean"] + (c["std"] or 0.0) >= best["mean"] - (best["std"] or 0.0)
        # the paper's number of every agent it has one for, rlu's cell or not (a sweep still
        # running, or an agent not run on this task, leaves the paper's column filled)
        beside = {a: paper_entry(task, a, ctx.paper) for a in ctx.agents}
        rows.append(
            {
                "task": task,
                "cells": cells,
                "paper": {a: e for a, e in beside.items() if e is not None},
            }
        )
    return {"rows": rows, "paper_columns": _paper_columns(ctx, rows)}


def _paper_columns(ctx: DomainContext, rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Per agent with a paper number in the table: the paper preset's budget and whether the
    paper's numbers are comparable with rlu's cells beside them: ``all``, ``some`` (the
    ``comparable`` cells only) or ``none`` (also when no row has both)."""
    out = {}
    for agent in ctx.agents:
        pairs = [r["cells"][agent] for r in rows if agent in r["paper"] and agent in r["cells"]]
        if not any(agent in r["paper"] for r in rows):
            continue
        n = sum(c["comparable"] for c in pairs)
        status = "all" if pairs and n == len(pairs) else "some" if n else "none"
        budget, stated = cond.budget_of(ctx.domain, ctx.presets.get(agent))
        out[agent] = {"budget": budget, "budget_stated": stated, "comparable": status}
    return out


def _aggregates(
    ctx: DomainContext,
    sel: Mapping[tuple[str, str], Selection],
    tasks: Sequence[str],
    protocol: Protocol,
) -> dict[str, Any]:
    """Per agent, the domain's statistic over ``tasks`` of the selected cells, its interval,
    and the IQM over the seeds every task has."""
    stat = domain_statistic(ctx.domain)
    agents: dict[str, Any] = {}
    for agent in ctx.agents:
        cells = [sel[(t, agent)] for t in tasks if (t, agent) in sel]
        if not cells:
            continue
        task_means = [c.mean for c in cells]
        est, (lo, hi) = task_bootstrap_interval(task_means, stat, reps=ctx.reps)
        entry: dict[str, Any] = {"tasks": len(cells), stat: est, "interval_25_75": [lo, hi]}
        common = sorted(set.intersection(*(set(c.seeds) for c in cells)))
        if common:
            matrix = np.array(
                [[dict(zip(c.seeds, c.scores, strict=True))[s] for c in cells] for s in common]
            )
            iqm, (ilo, ihi) = stratified_bootstrap_ci(matrix, "iqm", reps=ctx.reps)
            # over the seeds every task has (a sweep still running may have fewer on some):
            # with one seed in common the bootstrap has nothing to resample, so no interval
            ci = [ilo, ihi] if len(common) > 1 else None
            entry.update({"iqm": iqm, "iqm_ci95": ci, "iqm_seeds": len(common)})
        entry.update(_merge_sourced([_sourced(ctx, c, protocol) for c in cells]))
        agents[agent] = entry
    return {"tasks": list(tasks), "agents": agents}
