"""When one of rlu's numbers compares with the paper's: every condition the paper's number had,
each recorded by the runs and checked here.

The paper (Gulcehre et al. 2020, arXiv:2006.13888) is credited only with what it states, its
section or table cited (each domain's ``paper_conditions``, ``rlu.domains.paper``). Where it
states nothing (the continuous baselines' learner budget, the number of seeds, the evaluation
episodes), rlu's own choice stands in, named as rlu's (``Statement.rlu``), and every heading
that compares under it says "the paper states no ...". The conditions, in the order a cell's
label names the ones it misses:

- ``preset``: rlu's ``paper`` preset (the paper's appendix A settings; ``paper_recurrent`` on
  the three sequence tasks the paper gives LSTMs), changed only along the paper's grid;
- ``budget``: the learner steps, pre-training apart: the paper's 2M on Atari; elsewhere the
  paper states none and rlu's paper preset's ``num_steps`` stands in;
- ``data``: the release's own files: every shard of the task's dataset (continuous), or at least
  the 2M steps of the paper's Atari replay memory (which 2M it does not say);
- ``episodes``: evaluation episodes per run, at least rlu's 5 (the paper states none);
- ``seeds``: seeds behind the cell, at least rlu's 3 (the paper's tables print mean ± std
  without saying over how many runs);
- ``selection``: the protocol's inputs were themselves comparable: online selection chose among
  comparable runs of every configuration of the paper's grid; naive offline selection chose on
  comparable runs of every online-selection task of the domain.

Each check returns None (met) or the reason, in words, that the report prints.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from rlu.domains import DOMAINS
from rlu.domains.paper import CONTINUOUS, PaperConditions
from rlu.types import RluError

CONDITIONS = ("preset", "budget", "data", "episodes", "seeds", "selection")
"""Every condition, in the order a label names the missing ones."""

RUN_CONDITIONS = ("preset", "budget", "data", "episodes")
"""The conditions one run meets or not (the others are a cell's: its seeds, its selection)."""


@dataclass(frozen=True)
class PaperPreset:
    """What the report checks of an agent's ``paper`` preset (:func:`paper_preset` reads it
    from the agent module)."""

    steps: int | None
    """Learner steps of the preset (``num_steps``; Atari: ``atari.num_steps``)."""
    grid: Mapping[str, tuple[Any, ...]] = field(default_factory=dict)
    """The paper's grid (the agent module's ``GRID``): the only fields a comparable run
    changes, every combination of which online selection must have seen."""
    presets: tuple[str, ...] = ("paper",)
    """The agent's paper presets (``paper_recurrent`` where it has one)."""


def paper_conditions(domain: str) -> PaperConditions:
    """What the paper states of the conditions of a domain's numbers: its entry's
    ``paper_conditions``; a domain of the report's own (``other``), the continuous baselines'."""
    known = DOMAINS.get(domain)
    return known.paper_conditions if known is not None else CONTINUOUS


PAPER_TABLES = {name: d.paper_table for name, d in DOMAINS.items() if d.paper_table}
"""Where the paper's numbers beside each domain's cells come from."""


def budget_of(domain: str, preset: PaperPreset | None) -> tuple[int | None, bool]:
    """(the learner steps a comparable run trains, whether the paper states them): the paper's
    on Atari, else rlu's paper preset's (None: the report was not given it)."""
    stated = paper_conditions(domain).statements["budget"].paper
    if stated is not None:
        return int(stated), True
    return (None if preset is None else preset.steps), False


def _steps(n: int) -> str:
    for size, unit in ((1_000_000, "M"), (1_000, "k")):
        if n >= size:
            return f"{n / size:.{0 if n % size == 0 else 1}f}{unit}"
    return str(n)


def run_conditions(
    provenance: Mapping[str, Any],
    overrides: Mapping[str, Any] | None,
    task: str,
    domain: str,
    preset: PaperPreset | None,
) -> dict[str, str | None]:
    """The run conditions (:data:`RUN_CONDITIONS`) one run meets (None) or misses (why), from
    what it recorded (``numbers.run_provenance`` and its overrides; None: not recorded)."""
    return {
        "preset": _preset(provenance.get("preset"), overrides, task, domain, preset),
        "budget": _budget(provenance.get("steps"), domain, preset),
        "data": _data(provenance.get("data") or {}, domain),
        "episodes": at_least(provenance.get("eval_episodes"), "episodes", domain),
    }


def _preset(
    name: str | None,
    overrides: Mapping[str, Any] | None,
    task: str,
    domain: str,
    preset: PaperPreset | None,
) -> str | None:
    if preset is None:
        return "the report knows no paper preset of this agent"
    sequential = paper_conditions(domain).recurrent_tasks
    recurrent = task in sequential and "paper_recurrent" in preset.presets
    want = "paper_recurrent" if recurrent else "paper"
    if name != want:
        return f"preset {name or 'not recorded'}, not {want}"
    if overrides is None:
        return "its overrides of the preset were not recorded"
    off = [
        f"{k}={v}"
        for k, v in sorted(overrides.items())
        if k not in preset.grid or v not in preset.grid[k]
    ]
    if off:
        return f"the paper preset changed outside the paper's grid ({', '.join(off)})"
    return None


def _budget(steps: int | None, domain: str, preset: PaperPreset | None) -> str | None:
    budget, stated = budget_of(domain, preset)
    if budget is None:
        return "the paper preset's learner budget was not given to the report"
    if steps is None:
        return "learner steps not recorded"
    if steps != budget:
        if stated:
            return f"{steps:,} learner steps, not the paper's {_steps(budget)}"
        return f"{steps:,} learner steps, not rlu's {_steps(budget)} (the paper states no budget)"
    return None


def _data(data: Mapping[str, Any], domain: str) -> str | None:
    source = data.get("source", "unknown")
    if source != "release":
        return f"{source} data, not the release's"
    need = paper_conditions(domain).replay_steps
    if need is not None:
        steps = data.get("steps")
        if steps is None:
            return "the dataset's steps not recorded"
        if steps < need:
            return f"{steps:,} steps of the release, under the paper's {_steps(need)}-step replay"
        return None
    shards = data.get("shards")
    if not shards:
        return "the release shards it holds not recorded"
    if shards["of"] is None:
        return f"{data.get('files', 0)} files, none named as a release shard of the task"
    if shards["used"] < shards["of"]:
        return f"{shards['used']} of the release's {shards['of']} shards of the task"
    return None


def at_least(n: int | None, what: str, domain: str) -> str | None:
    """Seeds or evaluation episodes (``what``: ``seeds`` or ``episodes``) against the paper's
    number, or rlu's where the paper states none."""
    s = paper_conditions(domain).statements[what]
    need = s.paper if s.paper is not None else s.rlu
    noun = "seed" if what == "seeds" else "evaluation episode"
    if n is None:
        return f"{noun}s not recorded"
    if n < need:
        got = f"{n} {noun}{'s' * (n != 1)}"
        if s.paper is not None:
            return f"{got}, under the paper's {need}"
        return f"{got}, under rlu's {need} (the paper states no number of {noun}s)"
    return None


def missing(conditions: Mapping[str, str | None]) -> list[str]:
    """The names of the conditions a number misses, in :data:`CONDITIONS` order."""
    return [c for c in CONDITIONS if conditions.get(c)]


def merge(parts: Sequence[Mapping[str, str | None]]) -> dict[str, str | None]:
    """The conditions of a number made of several: each the first reason any part gives."""
    out: dict[str, str | None] = {}
    for c in CONDITIONS:
        reasons = list(dict.fromkeys(r for p in parts if (r := p.get(c))))
        out[c] = "; ".join(reasons) if reasons else None
    return out


def stand_ins(domain: str, preset_steps: Mapping[str, int | None]) -> list[str]:
    """What the paper states no number for in ``domain``, each with rlu's stand-in, in words
    (the report's intro and the heading of every comparison made under them)."""
    fam = paper_conditions(domain).statements
    out = []
    if fam["budget"].paper is None:
        steps = sorted({s for s in preset_steps.values() if s is not None})
        at = (
            f"rlu's {', '.join(_steps(s) for s in steps)} (its paper presets' learner steps)"
            if steps
            else "rlu's paper preset's learner steps (not given to the report)"
        )
        out.append(f"the paper states no learner budget: compared at {at}")
    for what, noun in (("seeds", "seeds"), ("episodes", "evaluation episodes")):
        if fam[what].paper is None:
            out.append(
                f"the paper states no number of {noun}: compared at rlu's {fam[what].rlu} or more"
            )
    return out


def needs(domain: str, preset_steps: Mapping[str, int | None]) -> dict[str, str]:
    """Per condition, what a comparable number of ``domain`` needs, in words: the paper's
    statement where it makes one, rlu's stand-in (named as rlu's) where it does not."""
    conditions = paper_conditions(domain)
    fam = conditions.statements
    if fam["budget"].paper is not None:
        budget = f"{_steps(int(fam['budget'].paper))} learner steps (the paper's)"
    else:
        per = ", ".join(f"{a} {_steps(s)}" for a, s in sorted(preset_steps.items()) if s)
        budget = (
            f"rlu's paper preset's learner steps ({per or 'not given to the report'}): "
            "rlu's choice, the paper states none"
        )
    if conditions.replay_steps is not None:
        need = _steps(conditions.replay_steps)
        data = (
            f"the release's files, at least the paper's {need} steps (which {need} is not stated)"
        )
    else:
        data = "every release shard of the task's dataset (the fraction is shown otherwise)"
    return {
        "preset": "rlu's paper preset (paper_recurrent on the three sequence tasks the paper "
        "gives LSTMs), changed only along the paper's grid",
        "budget": budget,
        "data": data,
        "episodes": f"at least rlu's {fam['episodes'].rlu} per run ({fam['episodes'].rlu_where}; "
        "the paper states none)",
        "seeds": f"at least rlu's {fam['seeds'].rlu} ({fam['seeds'].rlu_where}; the paper states "
        "none)",
        "selection": "inputs themselves comparable: online selection over comparable runs of "
        "every configuration of the paper's grid on the task; naive offline selection over "
        "comparable runs of every online-selection task of the domain",
    }


def paper_preset(agent: str, discrete: bool) -> Any:
    """What the report checks of an agent's ``paper`` preset
    (``rlu.report.PaperPreset``): its learner steps and the paper's grid (None: no
    such agent, no paper preset, or torch missing, so the agent module cannot be read)."""
    from rlu.agents import agent_module

    try:
        module = agent_module(agent, discrete)
    except (RluError, ImportError):
        return None
    config = module.PRESETS.get("paper")
    if config is None:
        return None
    steps = config.atari.num_steps if discrete else config.num_steps
    return PaperPreset(steps=int(steps), grid={k: tuple(v) for k, v in module.GRID.items()})
