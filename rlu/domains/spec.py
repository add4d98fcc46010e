"""What a task is: ``TaskSpec``, its release files (``ReleaseDataset``), a name's pick of one
(``TaskRef``). The domain modules build their tasks from these; ``rlu.tasks`` registers them and
re-exports every name here."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, TypeVar

from rlu.types import (
    ActionSpec,
    DiscreteSpec,
    ObservationSpec,
    RluError,
    observation_spec_to_json,
)

if TYPE_CHECKING:  # pragma: no cover
    import rlu.domains

_V = TypeVar("_V", bound=str | int)

Domain = str
"""A domain's name: one of ``rlu.domains.DOMAINS``."""


def _domains() -> Mapping[str, rlu.domains.Domain]:
    from rlu.domains import DOMAINS

    return DOMAINS


BUCKET = "rl_unplugged"
BASE_URL = "https://storage.googleapis.com/rl_unplugged"
# Gymnasium ids (TaskSpec.gym_id) and the entry point of their specs, a string so that a spec
# stored as JSON (Minari keeps one per dataset) makes the env again (rlu.envs.registration).
GYM_NAMESPACE = "rlu"
GYM_VERSION = 0
GYM_ENTRY_POINT = "rlu.envs.registration:make"


@dataclass(frozen=True)
class ReleaseDataset:
    """One family of files of the original release for a task.

    ``path`` is the object prefix inside the bucket, without the ``-%05d-of-%05d`` suffix, with
    ``{run}`` / ``{challenge}`` / ``{size}`` placeholders where the task has several datasets.
    ``shards`` maps a placeholder binding (e.g. ``"run_1"``, ``"none/large"``) or ``""`` to N.
    """

    family: str
    """The bucket's top folder: atari, atari_episodes_ordered, dm_control_suite, ..."""
    path: str
    shards: Mapping[str, int]
    seq_length: int | None = None
    """Steps per record for window files (2 or 40); None for whole-episode files."""
    folders: Mapping[str, str] = field(default_factory=dict)
    """A binding's named part -> its folder in the bucket where they differ (RWRL's paper sizes
    small / medium / large are the 20 / 40 / 100 percent folders)."""

    def prefix(self, binding: str = "") -> str:
        """``path`` with the dataset's placeholders filled: named ones (``{run}``, ...) and
        positional ones, the binding's ``/``-separated parts (bsuite's ``{0}`` and ``{1}``)."""
        named = {k: self.folders.get(v, v) for k, v in _binding_fields(binding).items()}
        return self.path.format(*binding.split("/"), **named)

    def shard_names(self, binding: str = "") -> list[str]:
        n = self.shards[binding]
        prefix = self.prefix(binding)
        return [f"{prefix}-{i:05d}-of-{n:05d}" for i in range(n)]


def _binding_fields(binding: str) -> dict[str, str]:
    if not binding:
        return {}
    if "/" not in binding:  # a run: Atari's run_N, DMLab's training_0
        return {"run": binding}
    challenge, size = binding.split("/")
    return {"challenge": challenge, "size": size}


@dataclass(frozen=True)
class TaskSpec:
    """Everything rlu knows about one task; datasets and envs both read it."""

    id: str
    domain: Domain
    name: str
    observation_spec: ObservationSpec
    action_spec: ActionSpec
    episode_length: int
    """Maximum agent steps per episode (time limit)."""
    selection: Literal["online", "offline"]
    episodes: Mapping[str, int]
    """Paper episode counts per dataset ("" for one dataset; "none/small" etc. for RWRL)."""
    release: tuple[ReleaseDataset, ...]
    env: Mapping[str, Any] = field(default_factory=dict)
    """Entry-point parameters for ``rlu.envs`` (suite domain/task, game, builder name)."""
    seq_length: int = 1
    """Paper sequence length (locomotion 2 or 40; 1 = transitions)."""
    datasets: tuple[str, ...] = ("",)
    """Dataset variants: Atari runs ``run_1..run_5``, RWRL ``none/small`` ... ``easy/large``."""

    @property
    def discrete(self) -> bool:
        """Whether the task's actions are discrete (Atari)."""
        return isinstance(self.action_spec, DiscreteSpec)

    @property
    def gym_id(self) -> str:
        """The task's Gymnasium id, ``rlu/DOMAIN-NAME-v0`` (registered by ``rlu.envs``; the
        domain is kept because RWRL and the control suite share task names)."""
        return f"{GYM_NAMESPACE}/{self.domain}-{self.name}-v{GYM_VERSION}"

    def max_episode_steps(self, env_settings: Mapping[str, Any] | None = None) -> int:
        """Agent steps after which the env made with ``env_settings`` truncates an episode
        (Gymnasium's ``spec.max_episode_steps``): ``episode_length``, or Atari's
        ``max_episode_steps`` setting."""
        setting = _domains()[self.domain].step_limit_setting
        if setting is not None and env_settings and setting in env_settings:
            return int(env_settings[setting])
        return self.episode_length

    @property
    def action_dim(self) -> int:
        """Discrete actions: how many; continuous: the action vector's size."""
        if isinstance(self.action_spec, DiscreteSpec):
            return self.action_spec.num_values
        return self.action_spec.size

    def release_dataset(self, family: str | None = None) -> ReleaseDataset:
        """The task's release dataset of ``family`` (None: its first, the default family); an
        unknown family raises an error listing the task's."""
        if family is None:
            return self.release[0]
        for r in self.release:
            if r.family == family:
                return r
        known = ", ".join(r.family for r in self.release)
        raise RluError(f"task {self.id!r} has no release family {family!r}; it has: {known}")

    def to_json(self) -> dict[str, Any]:
        """The task as JSON: what ``rlu info TASK --json`` and ``rlu list --json`` print."""
        return {
            "id": self.id,
            "domain": self.domain,
            "name": self.name,
            "selection": self.selection,
            "discrete": self.discrete,
            "action_dim": self.action_dim,
            "action_spec": self.action_spec.to_json(),
            "observation_spec": observation_spec_to_json(self.observation_spec),
            "episode_length": self.episode_length,
            "seq_length": self.seq_length,
            "episodes": dict(self.episodes),
            "datasets": list(self.datasets),
            "env": dict(self.env),
            "release": [
                {
                    "family": r.family,
                    "path": r.path,
                    "shards": dict(r.shards),
                    "seq_length": r.seq_length,
                }
                for r in self.release
            ],
        }


@dataclass(frozen=True)
class TaskRef:
    """A task as a name picked it, with the dataset settings the name carries (TFDS names do)."""

    task: TaskSpec
    name: str
    """The name as given (``control_suite/cartpole_swingup``, ``rlu_atari/Pong_run_1``)."""
    family: str | None = None
    """The release family the name reads (TFDS names), None: the task's default."""
    run: str | None = None
    """The run the name picks: Atari's ``run_N``, DMLab's ``training_0``."""
    challenge: str | None = None
    """RWRL challenge (``none`` / ``easy``) the name picks."""
    size: str | None = None
    """RWRL dataset size in the paper's words (``small`` / ``medium`` / ``large``)."""

    def dataset_settings(
        self,
        family: str | None = None,
        run: str | int | None = None,
        challenge: str | None = None,
        size: str | None = None,
    ) -> tuple[str | None, str | int | None, str | None, str | None]:
        """(family, run, challenge, size): what was passed, filled in from the name; a value
        that contradicts the name is an error naming both."""
        return (
            self._setting("family", family, self.family),
            self._setting("run", run, self.run),
            self._setting("challenge", challenge, self.challenge),
            self._setting("size", size, self.size),
        )

    def _setting(self, key: str, value: _V | None, mine: str | None) -> _V | str | None:
        """``value`` as passed, else the name's; one that contradicts the name is an error."""
        folders = {k: v for r in self.task.release for k, v in r.folders.items()}
        if value is not None and mine is not None and _norm(key, value, folders) != mine:
            raise RluError(
                f"{self.name} names {key} {mine!r}, which contradicts {key}={value!r}; drop "
                f"the {key} or use the task id {self.task.id}"
            )
        return value if value is not None else mine


def _norm(key: str, value: str | int, folders: Mapping[str, str]) -> str:
    """``value`` in the name's words: Atari's run 3 is run_3 (named runs such as DMLab's
    training_0 stay as they are); a bucket folder (RWRL's 20_percent) is the part it holds."""
    if key == "run":
        return f"run_{value}" if str(value).isdigit() else str(value)
    return {v: k for k, v in folders.items()}.get(str(value), str(value))
