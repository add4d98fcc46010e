"""The registry of domains: what is each domain's own, in one folder per domain.

    from rlu.domains import DOMAINS, get_domain
    DOMAINS["atari"].extra          # 'atari': the extra that installs its environments
    get_domain("rwrl").challenges   # ('none', 'easy')

A domain is one folder, ``rlu/domains/<name>/`` (a small one may be one module ``<name>.py``):

- ``__init__.py``: its task tables and TaskSpecs, and its entry ``DOMAIN`` (:class:`Domain`): the
  extra that installs its env, the TensorFlow Datasets builders that name its datasets and how
  their config names read, how its datasets are told apart (Atari runs, RWRL challenge and
  size), where its paper numbers come from, what the paper states of their conditions
  (``rlu.domains.paper``), how the report draws and normalises them, and the agent
  ``rlu generate`` trains to record its data at each scale;
- ``env.py``: its env factory, built of :mod:`rlu.domains.envkit` (imported only when an env is
  made);
- ``release.py``: its release families, built of :mod:`rlu.domains.records` (imported when the
  release is read).

The task registry (``rlu.tasks``), ``rlu.envs``, the release reader and catalog, the report,
generation and the command line read these entries instead of naming domains, so a new domain is
one folder plus one line in ``_MODULES`` below; ``tests/domains/test_domain_contract.py`` checks
every entry and ``tests/domains/test_new_domain.py`` adds one. The kits the domains are built of
(``envkit``, ``records``, ``common``, ``spec``, ``paper``) import nothing above them: no
``rlu.tasks``, ``rlu.data`` or ``rlu.envs`` (``tests/test_imports.py``).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal

from rlu.domains.paper import CONTINUOUS, TASK_FIGURES, PaperConditions
from rlu.types import RluError

if TYPE_CHECKING:  # pragma: no cover
    from rlu.domains.records import Family
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
    imported only when an env is made. Its envs end their own episodes, truncated at the task's
    ``max_episode_steps`` at the latest (evaluation adds no time limit of its own)."""
    extra: str
    """The pyproject extra that installs the env's packages."""
    packages: tuple[str, ...] = ()
    """Top-level modules its envs import: the command line names ``extra`` when one is missing."""
    mujoco: bool = False
    """Whether its envs are MuJoCo's (they need a GL backend to render)."""
    release_module: str | None = None
    """The module whose ``FAMILIES`` (:class:`rlu.domains.records.Family` entries) read and write
    the domain's release files, imported when the release is read (``rlu.data.release``); None:
    the domain has no release files."""
    env_install: str | None = None
    """How its env's packages are installed where no pip extra can (DeepMind Lab is built from
    source); None: ``extra`` installs them."""
    data_only: str | None = None
    """Why rlu makes no env of the domain, whose tasks are then data only (download, convert,
    train offline; ``rlu list`` and ``make_env`` say so); None: it has envs."""
    datasets: Literal["one", "runs", "challenge_size", "noise_run", "run_names"] = "one"
    """How a task's release datasets are told apart: one per task, Atari's ``run_N``, RWRL's
    ``challenge/size``, bsuite's ``noise/run`` (``--run 0.1/3``), DMLab's run folders by name
    (``--run training_0``)."""
    challenges: tuple[str, ...] = ()
    """Env challenges (``make_env(..., challenge=)``), the first the default; () takes none."""
    step_limit_setting: str | None = None
    """The env setting that changes the step limit (Atari's ``max_episode_steps``)."""
    vector_backend: str = "sync"
    """``make_vector_env``'s ``auto`` backend for the domain (see rlu.envs.vector)."""
    native_vector: str | None = None
    """The backend name of the domain's own vector env (Atari's ``"ale"``), made by its env
    module's ``make_vector(task, num_envs, seed, **settings)``; None: it has none."""
    tfds_builders: Mapping[str, str] = field(default_factory=dict)
    """TensorFlow Datasets builder -> the release family it reads."""
    tfds_examples: Mapping[str, str] = field(default_factory=dict)
    """Builder -> an example of its names, for error messages."""
    tfds_ref: Callable[..., TaskRef] | None = None
    """``(tasks, name, builder, config, family, fix) -> TaskRef``: the task of ``tasks`` (every
    registered task by id) a TFDS config names."""
    paper_table: str | None = None
    """Where the paper's numbers for the domain are (``rlu report``)."""
    statistic: Literal["mean", "median"] = "mean"
    """The paper's aggregate over the domain's tasks (median for Atari)."""
    paper_conditions: PaperConditions = CONTINUOUS
    """What the paper states of the conditions of its numbers for the domain, which the report
    checks each run against (rlu.domains.paper): the continuous baselines' (appendix A.1), or
    those of the domain's own family (Atari's, appendix A.2)."""
    normalised: bool = False
    """Scores are compared normalised, ``100 (score - random) / (best behaviour - random)``, as
    the paper compares Atari's: each task needs a random and a best-behaviour reference score
    (``rlu/resources``; ``rlu envs best-behaviour`` recomputes the latter from the release), and
    the report's aggregates, selection across tasks and figures are over normalised scores."""
    report_figures: tuple[str, ...] = TASK_FIGURES
    """The report's panels (``rlu.report.numbers.PANELS``) that draw the paper's figures of the
    domain: each task's bars, or Atari's normalised median, per-game improvement and the IQN and
    BCQ ablations."""
    stacked_frames: bool = False
    """Observations are frame stacks: datasets store each frame once and stack at sample time
    (Atari); the release's transition files hold whole stacks."""
    camera_setting: str | None = None
    """The env setting that turns its camera observation on or off (locomotion's ``camera``)."""
    generation: Literal["runs", "snapshots", "policy"] | None = None
    """How ``rlu generate`` makes its data: online agents' runs (``rlu.generate.recipe``), fixed
    behaviour snapshots of such runs rolled out under the domain's challenges (RWRL's recipe,
    ``rlu.generate.rwrl``), a policy the user supplies; None: not generated."""
    success: Literal["return", "time_limit", "none"] = "return"
    """What generation counts as a successful episode: a return of 80% of the maximum, reaching
    the time limit, or none (every episode kept)."""
    sim_packages: tuple[str, ...] = ()
    """Distributions the generated bytes depend on (recorded in a generated dataset's
    provenance)."""
    behaviour_agents: Mapping[str, str] = field(default_factory=dict)
    """Per scale of ``rlu generate`` (``rlu.generate.config.SCALES``: tiny, laptop, paper), the
    online agent whose runs record the data (``generation="runs"`` or ``"snapshots"``); each agent's
    settings at each scale are ``rlu.generate.scales``'; empty: no agent is trained."""

    def env_factory(self) -> Any:
        """The env module (imported now)."""
        return importlib.import_module(self.env_module)

    def release_families(self) -> tuple[Family, ...]:
        """The domain's release families (its release module imported now); () without one."""
        if self.release_module is None:
            return ()
        return tuple(importlib.import_module(self.release_module).FAMILIES)


# One line per domain: the package rlu/domains/<name>/ (or module <name>.py), whose DOMAIN is
# the entry.
_MODULES = ("control_suite", "locomotion", "atari", "rwrl", "bsuite", "dmlab")


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
