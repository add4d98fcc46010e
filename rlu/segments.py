"""The in-memory unit of the episode store: a time-ordered segment of steps (RLDS semantics).

A whole episode is a segment with ``is_first[0]`` and ``is_last[-1]``; a window of the original
release (2 or 40 steps) is a shorter segment whose flags say where, if anywhere, it touches an
episode boundary.

Step semantics (RLDS, SPEC §3), for step t of a segment of T steps:
- ``observation[t]`` is seen, ``action[t]`` is taken, ``reward[t]`` follows ``action[t]``;
- ``discount[t]`` is 0 when the transition t -> t+1 ends the episode in a terminal state, 1
  otherwise (a time-limit truncation keeps 1);
- the last step of an episode (``is_last``) holds the final observation; its action, reward and
  discount belong to no transition (stored as zeros; a terminal final step has ``is_terminal`` and
  discount 0), except that imports from d3rlpy dumps and D4RL files without next observations
  keep the last row of a truncated episode there, its action and reward (d3rlpy counts that
  reward in the episode's return; so does ``episode_return``);
- so a segment of T steps holds T - 1 transitions.

Atari data is stored as single frames ``(T, 84, 84)`` and stacked at sample time; such a segment
also carries ``frame_prefix``: the ``stack - 1`` frames before step 0 (zeros at an episode start,
as in the Dopamine replay that recorded the data).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rlu.types import Observation, SpecError

# Numeric per-segment metadata the store keeps as columns; other keys are rejected.
METADATA_FIELDS: Mapping[str, str] = {
    "episode_id": "uint64",
    "episode_return": "float64",
    "clipped_episode_return": "float64",
    "run": "int64",
    "seed": "int64",
    "checkpoint": "int64",
    "episode_index": "int64",
}
METADATA_MISSING = {"uint64": np.iinfo(np.uint64).max, "float64": np.nan, "int64": -1}


@dataclass(frozen=True)
class Segment:
    """One segment of steps (an episode, or a window of one) as in-memory arrays: the observation of
    every step, the action taken there and the reward and discount that followed, the flags, per-
    segment metadata (``episode_return``, run, ...) and, for frame-stacked Atari data, the frames
    before its first step (``frame_prefix``)."""

    observation: Observation
    action: np.ndarray
    reward: np.ndarray
    discount: np.ndarray
    is_first: np.ndarray
    is_last: np.ndarray
    is_terminal: np.ndarray
    metadata: Mapping[str, Any] = field(default_factory=dict)
    frame_prefix: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.reward.shape[0])

    @property
    def num_transitions(self) -> int:
        """Transitions in the segment: one fewer than its steps (the last step has no next one)."""
        return len(self) - 1


def make_episode(
    observations: Observation,
    actions: np.ndarray,
    rewards: np.ndarray,
    terminal: bool,
    metadata: Mapping[str, Any] | None = None,
    frame_prefix: np.ndarray | None = None,
) -> Segment:
    """A whole episode from T+1 observations and T actions / rewards (the env-loop view).

    ``terminal`` says whether the episode ended in a terminal state (discount 0 on the last
    transition) or was truncated by a time limit (discount 1). ``episode_return`` is filled in
    from the rewards unless given.
    """
    actions = np.asarray(actions)
    rewards = np.asarray(rewards, np.float32)
    n = rewards.shape[0]
    if actions.shape[0] != n:
        raise SpecError(f"episode has {n} rewards but {actions.shape[0]} actions; give one each")

    def check_obs(key: str, v: np.ndarray) -> None:
        if v.shape[0] != n + 1:
            raise SpecError(
                f"observation {key!r} has {v.shape[0]} steps; an episode of {n} actions needs "
                f"{n + 1} observations (the final one included)"
            )

    if isinstance(observations, Mapping):
        for k, v in observations.items():
            check_obs(k, np.asarray(v))
    else:
        check_obs("observation", np.asarray(observations))
    action = np.concatenate([actions, np.zeros_like(actions[:1])]) if n else actions[:0]
    if n == 0:
        action = np.zeros((1, *actions.shape[1:]), actions.dtype)
    discount = np.ones(n + 1, np.float32)
    discount[-1] = 0.0
    if terminal and n:
        discount[n - 1] = 0.0
    is_first = np.zeros(n + 1, bool)
    is_first[0] = True
    is_last = np.zeros(n + 1, bool)
    is_last[-1] = True
    is_terminal = np.zeros(n + 1, bool)
    is_terminal[-1] = bool(terminal)
    meta = dict(metadata or {})
    meta.setdefault("episode_return", float(rewards.sum(dtype=np.float64)))
    return Segment(
        observation=observations,
        action=action,
        reward=np.concatenate([rewards, np.zeros(1, np.float32)]),
        discount=discount,
        is_first=is_first,
        is_last=is_last,
        is_terminal=is_terminal,
        metadata=meta,
        frame_prefix=frame_prefix,
    )


@dataclass
class SegmentBatch:
    """N segments of one length T as stacked arrays (N, T, ...); iterating gives Segments."""

    observation: Any
    action: np.ndarray
    reward: np.ndarray
    discount: np.ndarray
    is_first: np.ndarray
    is_last: np.ndarray
    is_terminal: np.ndarray
    metadata: dict[str, np.ndarray] = field(default_factory=dict)
    lengths: np.ndarray | None = None
    """Per-segment step counts when some segments are shorter than T (trimmed windows)."""

    def __len__(self) -> int:
        return int(self.reward.shape[0])

    def __iter__(self) -> Iterator[Segment]:
        for i in range(len(self)):
            sl = slice(0, None if self.lengths is None else int(self.lengths[i]))
            obs = (
                {k: v[i, sl] for k, v in self.observation.items()}
                if isinstance(self.observation, Mapping)
                else self.observation[i, sl]
            )
            yield Segment(
                observation=obs,
                action=self.action[i, sl],
                reward=self.reward[i, sl],
                discount=self.discount[i, sl],
                is_first=self.is_first[i, sl],
                is_last=self.is_last[i, sl],
                is_terminal=self.is_terminal[i, sl],
                metadata={k: v[i].item() for k, v in self.metadata.items()},
            )
