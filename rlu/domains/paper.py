"""What the paper states of the conditions of its numbers, per family of its experiments: the
value of a domain's ``paper_conditions`` (``rlu.report.conditions`` checks every run against it).

The paper (Gulcehre et al. 2020, arXiv:2006.13888) is credited only with what it states, its
section or table cited. Where it states nothing (the continuous baselines' learner budget, the
number of seeds, the evaluation episodes), rlu's own choice stands in, named as rlu's
(``Statement.rlu``). :data:`CONTINUOUS` holds the continuous baselines' statements (appendix
A.1), which also stand for the domains the paper has no table for; a domain of its own family
(Atari, appendix A.2) builds its ``PaperConditions`` in its module.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any


@dataclass(frozen=True)
class Statement:
    """What the paper states of one condition (``paper`` None: nothing), where it says so, and
    the stand-in rlu compares at where it says nothing (``rlu``, named as rlu's choice)."""

    paper: Any
    where: str
    rlu: Any = None
    rlu_where: str = ""


@dataclass(frozen=True)
class PaperConditions:
    """The conditions of the paper's numbers for a family of its experiments."""

    statements: Mapping[str, Statement]
    """Per condition (``rlu.report.conditions.CONDITIONS``: preset, budget, data, episodes,
    seeds, selection), what the paper states of it, in that order."""
    replay_steps: int | None = None
    """The paper's fixed replay memory, in steps of the release (Atari's 2M): a comparable run's
    data holds at least this many; None: every release shard of the task's dataset."""
    discrete_agents: bool = False
    """Whether the paper's baselines are its discrete-action agents (Atari's): the report reads
    each agent's discrete paper preset, whose learner steps are ``atari.num_steps``."""
    recurrent_tasks: tuple[str, ...] = ()
    """Task ids whose paper preset is ``paper_recurrent``: the paper's "tasks of the sequential
    nature", whose networks add two LSTMs (appendix A.1)."""


NO_RUNS = "the paper's results tables (appendices B-D) print mean ± std without the number of runs"

EPISODES = Statement(
    None,
    "the paper states no number of evaluation episodes",
    rlu=5,
    rlu_where="rlu's default --eval-episodes",
)
"""Evaluation episodes per run: the paper states none, in any family."""

SEEDS = Statement(None, NO_RUNS, rlu=3, rlu_where="rlu's choice")
"""Seeds behind a number: the paper states none, in any family."""

CONTINUOUS = PaperConditions(
    MappingProxyType(
        {
            "preset": Statement(
                "the continuous baselines' settings",
                "appendix A.1 and its table 'Continuous control experiments hyperparameters'",
            ),
            "budget": Statement(
                None,
                "appendix A.1 gives no learner steps for the continuous baselines",
                rlu="the paper preset's num_steps",
                rlu_where="docs/paper_settings.md: 'learner steps | not stated | rlu's choice'",
            ),
            "data": Statement(
                "the task's dataset of the release",
                "section 3 (tables 'DM Control Suite tasks', 'DM Locomotion tasks')",
            ),
            "episodes": EPISODES,
            "seeds": SEEDS,
            "selection": Statement(
                "online policy selection per task over the grid; naive offline selection: the "
                "configuration best on average over the domain's online-selection tasks",
                "section 2.2 and section 4 ('Naive approach for offline policy selection')",
            ),
        }
    )
)
"""The continuous baselines' conditions (appendix A.1): every domain's, unless its entry names
others, and those of a domain the registry does not know (a report's ``other``)."""

TASK_FIGURES = ("task_bars",)
"""The report's figures of a domain the paper draws task by task (its control suite and
locomotion figures: each task's agents under the task's own protocol): every domain's, unless
its entry names others, and those of a domain the registry does not know."""
