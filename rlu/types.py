"""Specs, named batches and the Policy protocol shared by every part of rlu.

Data flows one way: ``TaskSpec -> data -> Batch -> agent.update`` and
``TaskSpec -> envs -> rollout(policy)``. This module is the only vocabulary they share, and it
imports numpy only.

Observations are either one array (Atari: uint8 (84, 84, 4), newest frame last) or a flat dict
keyed as in the original release without its ``observation/`` prefix, nested levels joined by
``/`` (``position``, ``walker/joints_pos``, ``walker/egocentric_camera``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import numpy as np

__all__ = [
    "BATCH_KINDS",
    "BATCH_LIMITS",
    "STATISTICS",
    "ActionSpec",
    "Agent",
    "ArraySpec",
    "BatchSpec",
    "BoundedSpec",
    "ConfigError",
    "DataStatistics",
    "DiscreteSpec",
    "FormatError",
    "Observation",
    "ObservationSpec",
    "Policy",
    "RluError",
    "Sequence",
    "SpecError",
    "Transition",
    "observation_spec_from_json",
    "observation_spec_to_json",
]


class RluError(Exception):
    """Base of every error rlu raises on bad input; the message names the thing and the fix."""


class FormatError(RluError):
    """A file is not in the format it claims to be (corrupt, truncated, wrong schema)."""


class ConfigError(RluError):
    """A configured value is outside its field's type or range (an agent config, composed
    settings, run settings): the message names the config, the field, the value, the bound and,
    where known, where the value came from (a file and key, or a flag)."""


class SpecError(RluError):
    """Data disagrees with a spec (shape, dtype, key)."""


@dataclass(frozen=True)
class ArraySpec:
    """Shape and dtype of one array (per step, without the batch or time axis)."""

    shape: tuple[int, ...]
    dtype: str
    """numpy dtype name: 'float32', 'uint8', 'int64', ..."""

    @property
    def size(self) -> int:
        """Elements of one array of this spec (the product of its shape)."""
        return int(np.prod(self.shape, dtype=np.int64))

    def zeros(self, *leading: int) -> np.ndarray:
        """Zeros of this spec with ``leading`` axes in front (batch, time)."""
        return np.zeros((*leading, *self.shape), dtype=self.dtype)

    def to_json(self) -> dict[str, Any]:
        """``{shape, dtype}`` (subclasses add their bounds or number of values)."""
        return {"shape": list(self.shape), "dtype": self.dtype}

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> ArraySpec:
        """The spec of ``to_json``'s output: ArraySpec, BoundedSpec or DiscreteSpec by its keys."""
        if "num_values" in d:
            return DiscreteSpec.from_json(d)
        if "minimum" in d:
            return BoundedSpec.from_json(d)
        return ArraySpec(tuple(int(x) for x in d["shape"]), str(d["dtype"]))


@dataclass(frozen=True)
class BoundedSpec(ArraySpec):
    """A continuous action: every element in [minimum, maximum]."""

    minimum: float = -1.0
    maximum: float = 1.0

    def to_json(self) -> dict[str, Any]:
        """``{shape, dtype, minimum, maximum}``."""
        return {**super().to_json(), "minimum": self.minimum, "maximum": self.maximum}

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> BoundedSpec:
        """The BoundedSpec of :meth:`to_json`'s output."""
        return BoundedSpec(
            tuple(int(x) for x in d["shape"]),
            str(d["dtype"]),
            float(d["minimum"]),
            float(d["maximum"]),
        )


@dataclass(frozen=True)
class DiscreteSpec(ArraySpec):
    """A discrete action: a scalar integer in [0, num_values)."""

    num_values: int = 2

    def to_json(self) -> dict[str, Any]:
        """``{shape, dtype, num_values}``."""
        return {**super().to_json(), "num_values": self.num_values}

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> DiscreteSpec:
        """The DiscreteSpec of :meth:`to_json`'s output."""
        return DiscreteSpec(
            tuple(int(x) for x in d["shape"]), str(d["dtype"]), int(d["num_values"])
        )


ObservationSpec = ArraySpec | Mapping[str, ArraySpec]
"""The spec of an observation: one array (Atari) or a flat dict of arrays keyed as the release."""
ActionSpec = BoundedSpec | DiscreteSpec
"""The spec of an action: bounded continuous, or discrete."""
Observation = np.ndarray | Mapping[str, np.ndarray]
"""An observation: one array, or a flat dict of arrays (batched: a leading batch axis on each)."""


def observation_spec_to_json(spec: ObservationSpec) -> Any:
    """An observation spec as JSON (one spec's ``to_json``, or a dict of them)."""
    if isinstance(spec, ArraySpec):
        return spec.to_json()
    return {k: v.to_json() for k, v in spec.items()}


def observation_spec_from_json(d: Any) -> ObservationSpec:
    """The observation spec of :func:`observation_spec_to_json`'s output."""
    if "shape" in d and "dtype" in d:
        return ArraySpec.from_json(d)
    return {k: ArraySpec.from_json(v) for k, v in d.items()}


class Transition(NamedTuple):
    """A batch of SARSA transitions (the paper's unified API), leading axis = batch.

    ``discount`` is 0 after a terminal transition and 1 otherwise (a time-limit truncation keeps 1);
    ``reward`` follows ``action``. For n-step batches ``reward`` is the discounted n-step sum,
    ``discount`` the product of the n per-step discounts (without the agent's gamma^n),
    ``next_observation`` the observation n steps later and ``next_action`` the action there.
    """

    observation: Observation
    action: np.ndarray
    reward: np.ndarray
    discount: np.ndarray
    next_observation: Observation
    next_action: np.ndarray


class Sequence(NamedTuple):
    """A batch of fixed-length windows, shape (batch, T, ...), padded past episode ends.

    ``mask[b, t]`` is True where step t is real data. Step semantics are RLDS: ``reward[b, t]``
    and ``discount[b, t]`` follow ``action[b, t]``; on the final step of an episode
    (``is_last``) action, reward and discount carry no information.
    """

    observation: Observation
    action: np.ndarray
    reward: np.ndarray
    discount: np.ndarray
    is_first: np.ndarray
    is_last: np.ndarray
    mask: np.ndarray
    return_to_go: np.ndarray | None = None
    """``return_to_go[b, t]``: the undiscounted sum of the rewards from step t to the end of its
    segment (a whole episode's remaining return; for window files, the window's), float32, 0
    where ``mask`` is False. Present when ``BatchSpec.return_to_go`` asks for it (the
    conditioning of return-conditioned agents: Decision Transformer), else None."""
    timestep: np.ndarray | None = None
    """``timestep[b, t]``: the step's index in its segment, int64, 0 where ``mask`` is False.
    Where segments are whole episodes (generated data, the ``*_episodes`` and
    ``atari_episodes_ordered`` families) it is the step's index in its episode; a window file's
    segment starts mid-episode, so there it counts from the window's first step. Present when
    ``BatchSpec.timestep`` asks for it (Decision Transformer's timestep embedding), else None."""


class Policy(Protocol):
    """What evaluation sees of an agent: a batch of observations in, a batch of actions out.

    ``is_first[i]`` is True where row i's episode starts at this observation, so a recurrent
    policy restarts its state there; the batch always has the same rows (one per env).
    ``reward[i]`` (float64) is the reward row i got for the action it took at the previous
    call, 0 where ``is_first``: a return-conditioned policy (Decision Transformer) lowers its
    return to go by it; every other policy accepts and ignores it."""

    def __call__(
        self, observation: Observation, is_first: np.ndarray, reward: np.ndarray
    ) -> np.ndarray: ...


BATCH_KINDS = ("transition", "sequence")
"""The batches an agent may ask for (``BatchSpec.kind``): transitions or sequences."""
STATISTICS = ("observation", "reward", "return")
"""Dataset statistics an agent may ask for (``BatchSpec.statistics``; ``DataStatistics``)."""
BATCH_LIMITS = {"batch_size": 1 << 20, "n_step": 1000, "sequence_length": 100_000}
"""Largest values a BatchSpec takes (a batch of 1M rows already holds gigabytes of Atari
frames; larger values are typing mistakes that would end in an out-of-memory kill)."""


@dataclass(frozen=True)
class BatchSpec:
    """What an agent needs from the data, declared once by the agent (``agent.batch_spec``) and
    consumed as is by ``rlu.data.make_sampler(dataset, spec, seed)``: the training loop, the
    online behaviour loop and user code build their samplers from it, never from probes.

    n-step convention (one place, shared by the data layer and every agent): a ``Transition``
    sampled with ``n_step = n`` has ``reward = sum_{i<n} gamma^i (prod_{j<i} d_j) r_i`` (per-step
    rewards clipped to ``reward_clip`` first) and ``discount = prod_{i<n} d_i``; the agent
    bootstraps with ``bootstrap_gamma * discount`` (``gamma ** n``).
    """

    batch_size: int
    """Transitions (or windows, for sequences) per batch."""
    kind: str = "transition"
    """'transition' (SARSA tuples, optionally n-step) or 'sequence' (windows with a mask)."""
    n_step: int = 1
    """Steps summed into a transition's reward (transition batches only)."""
    gamma: float = 1.0
    """Per-step discount of the n-step reward sum; the agent's own gamma."""
    sequence_length: int = 1
    """Window length of sequence batches."""
    reward_clip: float | None = None
    """Per-step rewards are clipped to [-reward_clip, reward_clip] before anything else (the
    paper's Atari agents learn from rewards clipped to [-1, 1]); None keeps them as stored."""
    statistics: tuple[str, ...] = ()
    """What the agent needs computed from the whole dataset before its first update, among
    ``STATISTICS`` (TD3+BC's observation normalisation: ``("observation",)``). The loop computes
    them once (``rlu.data.statistics``) and hands them to ``agent.set_statistics``, which an
    agent that names any must have; the agent keeps them in its state."""

    return_to_go: bool = False
    """Sequence batches only: also give each step's return to go (``Sequence.return_to_go``)."""
    timestep: bool = False
    """Sequence batches only: also give each step's index in its segment (``Sequence.timestep``)."""

    def __post_init__(self) -> None:
        if self.kind not in BATCH_KINDS:
            raise SpecError(f"BatchSpec.kind={self.kind!r}; use one of {', '.join(BATCH_KINDS)}")
        for name, most in BATCH_LIMITS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
                raise SpecError(f"BatchSpec.{name}={value!r}; it must be an integer >= 1")
            if value > most:
                raise SpecError(f"BatchSpec.{name}={value!r}; at most {most:,} (a larger value "
                                "would not fit in memory)")  # fmt: skip
        if not 0.0 <= float(self.gamma) <= 1.0:
            raise SpecError(f"BatchSpec.gamma={self.gamma!r}; a discount lies in [0, 1]")
        unknown = sorted(set(self.statistics) - set(STATISTICS))
        if unknown:
            raise SpecError(
                f"BatchSpec.statistics names {unknown}; the data gives {', '.join(STATISTICS)}"
            )
        for name in ("return_to_go", "timestep"):
            if getattr(self, name) and self.kind != "sequence":
                raise SpecError(
                    f"BatchSpec.{name} applies to sequence batches; set kind='sequence'"
                )
        if self.reward_clip is not None and not float(self.reward_clip) > 0.0:
            raise SpecError(
                f"BatchSpec.reward_clip={self.reward_clip!r}; use a positive bound or None"
            )

    @property
    def bootstrap_gamma(self) -> float:
        """The factor of ``discount * V(next_observation)`` in an n-step target: gamma^n."""
        return float(self.gamma) ** self.n_step


@dataclass(frozen=True)
class DataStatistics:
    """Statistics of a whole dataset, computed once before training for an agent that asks for
    them (``BatchSpec.statistics``); a field the agent did not ask for is None.

    ``observation``: per-feature mean and standard deviation of every observation (a dict of
    arrays for dict observations, float features only: image keys are left out), over every
    step of the dataset. ``reward``: mean, standard deviation, minimum and maximum of the
    per-step rewards. ``return``: minimum and maximum undiscounted return over the dataset's
    whole episodes (IQL's and CORL's reward scaling, ``1000 / (max - min)``)."""

    observation_mean: Observation | None = None
    observation_std: Observation | None = None
    reward_mean: float | None = None
    reward_std: float | None = None
    reward_min: float | None = None
    reward_max: float | None = None
    return_min: float | None = None
    return_max: float | None = None


class Agent(Protocol):
    """The contract every agent in ``rlu.agents`` meets (one file each; see docs/agents.md).

    Built as ``Agent(observation_spec, action_spec, config, seed=..., device="cpu")``: its
    modules, random draws and batches live on ``device`` (``resolve_device``), and ``update``
    takes numpy batches or tensors already on that device. ``batch_spec`` says what
    batches ``update`` takes; ``act`` maps a batched observation (leading batch axis) to a batch
    of actions, and ``is_first`` (bool, one per row) marks rows whose episode starts at this
    observation, so recurrent agents restart their state there (others ignore it); ``reward``
    (one per row) is what each row got for the action it took at the previous call, 0 where
    ``is_first`` (the rollout's ``Policy`` argument): a return-conditioned agent (Decision
    Transformer) lowers its return to go by it and refuses to continue a row without it, every
    other agent ignores it.
    ``num_steps`` is the learner steps of a full run of its config (what ``rlu train`` runs
    without --steps); ``pretrain_steps`` counts the updates of a pre-training phase (BRAC's
    behaviour model; 0 for most agents) that the loop runs before, and on top of, them.
    ``modules`` names every torch module the agent owns (targets included) and ``state_dict()``
    holds everything needed to resume bit for bit (plain tensors, numbers and
    dicts: checkpoints load with ``weights_only=True``), as a snapshot that later updates leave
    alone; ``load_state_dict`` copies what it is given, so agents loaded from one state in
    memory share no tensor. An agent whose ``batch_spec.statistics`` names any also has
    ``set_statistics(stats: DataStatistics)``, called once before the first update of a new
    run (a resumed run restores them with its state).
    """

    config: Any
    batch_spec: BatchSpec
    num_steps: int
    pretrain_steps: int
    modules: Mapping[str, Any]
    device: Any

    def update(self, batch: Any) -> dict[str, float]:
        """One learner step on ``batch`` (what ``batch_spec`` says: numpy arrays or tensors on
        the agent's device); returns the step's metrics (losses, ...) as floats."""
        ...

    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """Actions for a batch of observations (leading batch axis): the greedy policy, or its
        exploration with ``greedy=False``; ``is_first`` marks rows whose episode starts here and
        ``reward`` is each row's reward for its previous action (0 where ``is_first``)."""
        ...

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume bit for bit (plain tensors, numbers and dicts), as a
        snapshot that later updates leave alone."""
        ...

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Load a :meth:`state_dict`, copying what it is given."""
        ...
