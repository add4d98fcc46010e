"""The one registry of every RL Unplugged task: datasets and environments are built from it.

Sources for every number here:
- observation keys, dims and action dims: the ``shapes`` tables of the original
  ``rl_unplugged/dm_control_suite.py`` (github.com/deepmind/deepmind-research);
- selection split, episode counts, sequence lengths: the paper's tables 1-4 (Gulcehre et al.
  2020, arXiv:2006.13888);
- release paths and shard counts: the release bucket's layout, as the original loaders
  (``rl_unplugged/*.py``) name them;
- Atari minimal action-set sizes: read from ale-py 0.12.1 (``tests/test_tasks.py`` re-checks them
  against ALE when the ``atari`` extra is installed).

Names: every function that takes a task id (``get_task``, ``resolve_task`` and all that call
them) also takes a bare name when it is unambiguous (``walker_walk`` is not: control suite and
RWRL both have it) and TensorFlow Datasets' names for RL Unplugged (``TFDS_BUILDERS``):
``rlu_control_suite/cartpole_swingup``, ``rlu_locomotion/rodent_gaps``, ``rlu_atari/Pong_run_1``
(also ``rlu_atari_checkpoints_ordered/...``), ``rlu_rwrl/walker_walk_combined_challenge_easy_
100_percent``, with or without a ``:VERSION`` suffix. A TFDS name also picks the dataset TFDS
builds from: the release family it reads (``dm_control_suite_episodes``, the whole-episode
files, for ``rlu_control_suite``) and the Atari run or RWRL challenge and size
(``TaskRef.dataset_settings``).
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from rlu.domains import DOMAINS as _REGISTRY
from rlu.domains.atari import (  # noqa: F401 - the registry's names, as before
    ATARI_FRAME_STACK,
    ATARI_MAX_AGENT_STEPS,
    ATARI_NUM_ACTIONS,
    ATARI_OBSERVATION,
    ATARI_OFFLINE,
    ATARI_ONLINE,
    ATARI_RUNS,
)
from rlu.domains.common import act, f32, obs
from rlu.domains.rwrl import RWRL_DATASETS, RWRL_EASY_DUMMY_KEYS, RWRL_SIZES  # noqa: F401
from rlu.domains.rwrl import observation_spec as _rwrl_observation_spec
from rlu.domains.spec import (  # noqa: F401 - defined with the domains, named here as before
    BASE_URL,
    BUCKET,
    GYM_ENTRY_POINT,
    GYM_NAMESPACE,
    GYM_VERSION,
    Domain,
    ReleaseDataset,
    TaskRef,
    TaskSpec,
    _binding_fields,
    _norm,
)
from rlu.types import (
    ActionSpec,
    ArraySpec,
    DiscreteSpec,
    ObservationSpec,
    RluError,
)

DOMAINS: tuple[str, ...] = tuple(_REGISTRY)
_f32 = f32
_obs = obs
_act = act


def _build() -> dict[str, TaskSpec]:
    tasks: dict[str, TaskSpec] = {}
    for domain in _REGISTRY.values():
        for task in domain.build_tasks():
            if task.domain != domain.name or task.id in tasks:
                raise RluError(
                    f"domain {domain.name!r} builds task {task.id!r} twice or as another's"
                )
            tasks[task.id] = task
    return tasks


TASKS: Mapping[str, TaskSpec] = MappingProxyType(_build())


def rwrl_observation_spec(task: TaskSpec, challenge: str) -> Mapping[str, ArraySpec]:
    """Observation spec of an RWRL task under a challenge (``easy`` adds 10 dummy scalars)."""
    return _rwrl_observation_spec(task, challenge)


# --- names: ids, bare names and TensorFlow Datasets' names --------------------------------------
# TFDS builder -> (rlu domain, the release family the builder reads). Sources: tensorflow_datasets
# rl_unplugged/<builder>/<builder>.py ``_INPUT_FILE_PREFIX`` and ``BUILDER_CONFIGS`` (config names
# ``<task>``, ``<Game>_run_<N>``, ``<domain>_<task>_combined_challenge_<none|easy>_<P>_percent``).
TFDS_BUILDERS: Mapping[str, tuple[str, str]] = MappingProxyType(
    {b: (d.name, fam) for d in _REGISTRY.values() for b, fam in d.tfds_builders.items()}
)
_TFDS_VERSION = re.compile(r":\d+(\.\d+)*$")


def resolve_task(name: str) -> TaskRef:
    """The task ``name`` names (an id, an unambiguous bare name or a TFDS name), with the dataset
    settings a TFDS name carries; an unknown name raises an error listing the closest ids."""
    if name in TASKS:
        return TaskRef(TASKS[name], name)
    builder = name.split("/", 1)[0]
    if builder in TFDS_BUILDERS or builder.startswith("rlu_"):
        return _resolve_tfds(name)
    # Accept a bare name when it is unambiguous ("cartpole_swingup" -> control_suite/...).
    bare = [t for t in TASKS.values() if t.name.lower() == name.lower()]
    if len(bare) == 1:
        return TaskRef(bare[0], name)
    needle = name.split("/")[-1].lower()
    close = [t.id for t in TASKS.values() if needle and needle in t.id.lower()][:5]
    if not close:
        close = difflib.get_close_matches(name, list(TASKS), n=5, cutoff=0.6)
    if not close:
        close = difflib.get_close_matches(
            name.split("/")[-1], [t.name for t in TASKS.values()], n=5, cutoff=0.4
        )
        close = [t.id for t in TASKS.values() if t.name in close]
    hint = f" Closest: {', '.join(close)}." if close else ""
    raise RluError(f"unknown task id {name!r}.{hint} `rlu list` prints every id.")


_TFDS_EXAMPLES = {b: e for d in _REGISTRY.values() for b, e in d.tfds_examples.items()}


def _resolve_tfds(name: str) -> TaskRef:
    builder, _, config = _TFDS_VERSION.sub("", name).partition("/")
    if builder not in TFDS_BUILDERS:
        if builder == "rlu_atari_checkpoints":
            why = (
                "it reads the atari_episodes_v2 files, which rlu does not read; rlu reads the "
                "files of rlu_atari and rlu_atari_checkpoints_ordered (atari_episodes_ordered), "
                "e.g. rlu_atari/Pong_run_1"
            )
        else:
            why = f"rlu knows the TFDS builders {', '.join(TFDS_BUILDERS)}"
        raise RluError(f"{name!r}: TFDS builder {builder!r} has no rlu task: {why}")
    domain, family = TFDS_BUILDERS[builder]
    fix = f"TFDS names read like {_TFDS_EXAMPLES[builder]} (`rlu list --domain {domain}`)"
    if not config:
        raise RluError(f"{name!r} names no config; {fix}")
    ref = _REGISTRY[domain].tfds_ref
    if ref is None:  # pragma: no cover - a builder is registered with its domain's reader
        raise RluError(f"{name!r}: domain {domain!r} reads no TFDS names")
    return ref(TASKS, name, builder, config, family, fix)


def get_task(task_id: str) -> TaskSpec:
    """The TaskSpec of ``task_id`` (an id, a bare name or a TFDS name: ``resolve_task``)."""
    return resolve_task(task_id).task


def list_tasks(domain: str | None = None, selection: str | None = None) -> list[TaskSpec]:
    """Every TaskSpec, optionally filtered by domain and selection split."""
    if domain is not None and domain not in DOMAINS:
        raise RluError(f"unknown domain {domain!r}; use one of {', '.join(DOMAINS)}")
    return [
        t
        for t in TASKS.values()
        if (domain is None or t.domain == domain)
        and (selection is None or t.selection == selection)
    ]


def check_challenge(task: str, challenge: str, keys: set[str], recorded: str, what: str) -> None:
    """An RWRL policy runs only where the env gives the observation keys its data had (the easy
    challenge adds dummy observations): refuse a challenge whose keys differ."""
    wanted = set(rwrl_observation_spec(get_task(task), challenge))
    if wanted != keys:
        differ = sorted(wanted ^ keys)
        raise RluError(
            f"{what} was recorded under RWRL challenge {recorded!r}; challenge {challenge!r} gives "
            f"other observations ({', '.join(differ[:4])}{' ...' if len(differ) > 4 else ''}), so "
            f"its policies cannot run there: evaluate under {recorded!r} (drop --challenge)"
        )


def _spec_text(spec: ObservationSpec | ActionSpec) -> str:
    if isinstance(spec, Mapping):
        return "{" + ", ".join(f"{k}: {tuple(v.shape)}" for k, v in sorted(spec.items())) + "}"
    if isinstance(spec, DiscreteSpec):
        return f"{spec.num_values} discrete actions"
    return str(tuple(spec.shape))


def check_data_matches(
    task_id: str,
    observation_spec: ObservationSpec,
    action_spec: ActionSpec,
    what: str,
    recorded_task: str | None = None,
    challenge: str = "none",
) -> None:
    """Refuse, before any training step, a dataset whose observations or actions are not those
    of ``task_id``'s env (``what`` names the dataset; ``recorded_task``: the task its manifest
    names). Observations are compared as the agent sees them (Atari: stacked frames)."""
    task = get_task(task_id)
    fix = f"train --task {recorded_task} on it" if recorded_task else "pass the dataset's own task"
    if recorded_task and recorded_task in TASKS and TASKS[recorded_task].id != task.id:
        raise RluError(
            f"{what} holds data of task {recorded_task}, not {task.id}: {fix}, or give a "
            f"dataset of {task.id}"
        )
    want_obs = (
        rwrl_observation_spec(task, challenge)
        if _REGISTRY[task.domain].challenges
        else task.observation_spec
    )

    def shapes(spec: ObservationSpec) -> Any:
        if isinstance(spec, Mapping):
            return {k: tuple(v.shape) for k, v in spec.items()}
        return tuple(spec.shape)

    if shapes(observation_spec) != shapes(want_obs):
        raise RluError(
            f"{what}: its observations {_spec_text(observation_spec)} are not those of "
            f"{task.id}'s env {_spec_text(want_obs)}; {fix}, or give a dataset of {task.id}"
        )
    want_act = task.action_spec
    same = type(action_spec) is type(want_act) and tuple(action_spec.shape) == tuple(want_act.shape)
    if same and isinstance(want_act, DiscreteSpec):
        same = action_spec.num_values == want_act.num_values  # type: ignore[union-attr]
    if not same:
        raise RluError(
            f"{what}: its actions ({_spec_text(action_spec)}) are not those of {task.id}'s env "
            f"({_spec_text(want_act)}); {fix}, or give a dataset of {task.id}"
        )
