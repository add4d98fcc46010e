"""The registry of domains: what is each domain's own, in one module per domain.

    from rlu.domains import DOMAINS, get_domain
    DOMAINS["atari"].extra          # 'atari': the extra that installs its environments
    get_domain("rwrl").challenges   # ('none', 'easy')

A domain's module (``rlu/domains/<name>.py``) holds its task tables and builds its TaskSpecs,
names its env factory (imported only when an env is made) and the extra that installs it, the
TensorFlow Datasets builders that name its datasets and how their config names read, how its
datasets are told apart (Atari runs, RWRL challenge and size), and where its paper numbers come
from. The task registry (``rlu.tasks``), ``rlu.envs``, the release catalog, the report and the
command line read these entries instead of naming domains, so a new domain is one module plus one
line in ``_MODULES`` below; ``tests/domains/test_domain_contract.py`` checks every entry.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal

from rlu.types import RluError

if TYPE_CHECKING:  # pragma: no cover
    from rlu.domains.spec import TaskRef, TaskSpec

__all__ = ["Domain", "DOMAINS", "get_domain"]


@dataclass(frozen=True)
class Domain:
    """One domain of the suite: its tasks and everything else that is its own."""

    name: str
    """The domain's name: the first part of its task ids (``atari/Pong``)."""
    title: str
    """The domain's name in prose (reports, ``rlu list``)."""
    build_tasks: Callable[[], list[TaskSpec]]
    """The domain's TaskSpecs (called once, by ``rlu.tasks``)."""
    env_module: str
    """The module whose ``make(task, seed=..., render=..., **settings)`` makes its envs,
    imported only when an env is made."""
    extra: str
    """The pyproject extra that installs the env's packages."""
    packages: tuple[str, ...] = ()
    """Top-level modules its envs import: the command line names ``extra`` when one is missing."""
    mujoco: bool = False
    """Whether its envs are MuJoCo's (they need a GL backend to render)."""
    datasets: Literal["one", "runs", "challenge_size"] = "one"
    """How a task's release datasets are told apart: one per task, Atari's ``run_N``, RWRL's
    ``challenge/size``."""
    challenges: tuple[str, ...] = ()
    """Env challenges (``make_env(..., challenge=)``), the first the default; () takes none."""
    step_limit_setting: str | None = None
    """The env setting that changes the step limit (Atari's ``max_episode_steps``)."""
    vector_backend: str = "sync"
    """``make_vector_env``'s ``auto`` backend for the domain (see rlu.envs.vector)."""
    tfds_builders: Mapping[str, str] = field(default_factory=dict)
    """TensorFlow Datasets builder -> the release family it reads."""
    tfds_examples: Mapping[str, str] = field(default_factory=dict)
    """Builder -> an example of its names, for error messages."""
    tfds_ref: Callable[..., TaskRef] | None = None
    """``(tasks, name, builder, config, family, fix) -> TaskRef``: the task of ``tasks`` (every
    registered task by id) a TFDS config names."""
    paper_table: str | None = None
    """Where the paper's numbers for the domain are (``rlu report``)."""

    def env_factory(self) -> Any:
        """The env module (imported now)."""
        return importlib.import_module(self.env_module)


# One line per domain: the module rlu/domains/<name>.py, whose DOMAIN is the entry.
_MODULES = ("control_suite", "locomotion", "atari", "rwrl")


def _load() -> Mapping[str, Domain]:
    out = {}
    for module in _MODULES:
        domain = importlib.import_module(f"rlu.domains.{module}").DOMAIN
        if not isinstance(domain, Domain) or domain.name != module:
            raise RluError(f"rlu.domains.{module}.DOMAIN must be a Domain named {module!r}")
        out[module] = domain
    return MappingProxyType(out)


DOMAINS: Mapping[str, Domain] = _load()
"""Every domain by name, in ``rlu list``'s order."""


def get_domain(name: str) -> Domain:
    """The Domain ``name``; an unknown name raises an error listing the domains."""
    if name not in DOMAINS:
        raise RluError(f"unknown domain {name!r}; use one of {', '.join(DOMAINS)}")
    return DOMAINS[name]
