"""Vectorised views of a stored dataset: SARSA and n-step transitions, sequences, frame stacks.

Every view turns an array of indices into a named batch with numpy fancy indexing, with no
per-step Python; the one Python loop is the store's, for zlib-compressed image columns, which
inflate each distinct frame of a batch once, reading each run of adjacent frames (a stacked
transition's) in one read, split between the calling thread and one helper process per other
core (``rlu.data.store.decoders``). Indices are *eligible start steps*, numbered
per view:

- transitions: every step that is not the last step of its segment (a segment of T steps holds
  T - 1 transitions: ``(o_t, a_t, r_t, d_t, o_t+1, a_t+1)``, the paper's SARSA tuple);
- n-step transitions: steps t whose n-step window fits in the segment, or whose segment ends in a
  terminal state inside the window (past a terminal, rewards are 0 and the discount stays 0). A
  window that would cross a truncated end is left out, so every sample bootstraps exactly n steps
  ahead: the target is ``reward + gamma**n * discount * Q(next_observation, next_action)``;
- sequences: windows of ``length`` steps starting every ``stride`` steps of a segment (at least one
  window per segment), padded past the segment's end with zeros and ``mask`` False.

Atari frames (``frame_stack > 1``) are stored once and stacked here: the observation of step t is
frames ``t - stack + 1 .. t`` on the last axis, newest last. Frames before an episode's first step
are zeros (stored as the segment's frame prefix, as in the Dopamine replay that recorded the data),
so a stack never mixes two episodes.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import numpy as np

from rlu.data.store import Dataset, ZlibColumn, open_dataset
from rlu.types import ArraySpec, BatchSpec, Observation, RluError, Sequence, Transition


def _take(col: np.ndarray | ZlibColumn, rows: np.ndarray) -> np.ndarray:
    """``col[rows]`` along the first axis (``rows`` of any shape). ``np.take`` gathers the same
    rows as fancy indexing, faster on every batch kind but stacked frames, where the copy
    dominates (bench/sampling.py; the figures: bench/README.md, "Design choices")."""
    if isinstance(col, ZlibColumn):
        return col.take(rows)
    return np.take(col, rows, axis=0)


# --- the maths every transition source shares (the online replay of rlu.generate too) -------
def n_step_counts(length: np.ndarray, terminal_end: np.ndarray | None, n: int) -> np.ndarray:
    """How many n-step transitions start in each segment of ``length`` steps: every step but the
    last when the segment ends in a terminal state (``terminal_end``; None only when ``n`` is 1),
    else only the steps whose window of ``n`` transitions fits before its end (a window never
    crosses a truncation)."""
    length = np.asarray(length, np.int64)
    if n == 1:
        return np.maximum(length - 1, 0)
    if terminal_end is None:
        raise RluError(f"n-step counts for n={n} need the segments' terminal_end")
    return np.maximum(np.where(terminal_end, length - 1, length - n), 0)


def n_step_targets(
    reward: np.ndarray,
    discount: np.ndarray,
    t: np.ndarray,
    last: np.ndarray,
    n: int,
    gamma: float,
    reward_clip: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(reward, discount, next step)`` of the n-step transitions that start at steps ``t`` of
    the step columns ``reward`` and ``discount``, each in a segment whose last step is ``last``
    (same shape as ``t``).

    ``reward = sum_i gamma^i (prod_{j<i} d_{t+j}) r_{t+i}`` and ``discount = prod_i d_{t+i}``
    over ``i < n``, the convention of :class:`rlu.types.Transition` (the agent bootstraps with
    ``gamma^n``); steps past the segment's last transition count as reward 0 and discount 0
    (they follow a terminal state); the next step is ``min(t + n, last)``. Rewards are clipped to
    ``+-reward_clip`` per step, before the sum (``BatchSpec.reward_clip``).
    """

    def rewards(steps: np.ndarray) -> np.ndarray:
        r = np.take(reward, steps, axis=0)
        return r if reward_clip is None else np.clip(r, -reward_clip, reward_clip)

    if n == 1:
        return rewards(t), np.take(discount, t, axis=0), t + 1
    window = t[:, None] + np.arange(n)
    valid = window < last[:, None]  # steps that hold a transition
    window = np.minimum(window, last[:, None])
    r = np.where(valid, rewards(window), 0.0)
    d = np.where(valid, np.take(discount, window, axis=0), 0.0)
    # weight of r_{t+i}: gamma^i * prod_{j<i} d_{t+j}
    alive = np.cumprod(np.concatenate([np.ones((len(t), 1)), d[:, :-1]], axis=1), axis=1)
    out_reward = (r * alive * gamma ** np.arange(n)).sum(axis=1).astype(np.float32)
    return out_reward, np.prod(d, axis=1).astype(np.float32), np.minimum(t + n, last)


def stack_frames(frames: np.ndarray | ZlibColumn, first: np.ndarray, k: int) -> np.ndarray:
    """Frame stacks from frames stored once: the stack whose oldest frame is row ``first`` (any
    shape of indices) holds rows ``first .. first + k - 1`` on a new last axis, newest last. An
    episode's frames are stored after ``k - 1`` frames of zeros, so a stack never mixes two."""
    return np.moveaxis(_take(frames, first[..., None] + np.arange(k)), -3, -1)


class _Index:
    """Maps eligible-start numbers to global steps: ``counts[s]`` starts in segment s, the k-th
    of them at ``start[s] + k * stride``."""

    def __init__(self, ds: Dataset, counts: np.ndarray, stride: int = 1):
        self.start = np.asarray(ds.start, np.int64)
        self.counts = counts.astype(np.int64)
        self.cum = np.concatenate([[0], np.cumsum(self.counts)])
        self.stride = stride
        self.size = int(self.cum[-1])
        # Guide table: the segment holding id b * width, so that locating an id is one gather
        # plus a few vectorised steps forward instead of a binary search (faster on large
        # datasets: bench/README.md, "Design choices").
        self.width = max(1, self.size // max(1, len(self.counts)))
        buckets = np.arange(0, max(self.size, 1), self.width)
        self.guide = np.searchsorted(self.cum, buckets, side="right") - 1

    def locate(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(segment, global step) of eligible starts ``ids``."""
        ids = np.asarray(ids, np.int64)
        if ids.size and (ids.min() < 0 or ids.max() >= self.size):
            raise IndexError(f"start ids must lie in [0, {self.size})")
        seg = self.guide[ids // self.width]
        for _ in range(8):
            step = self.cum[seg + 1] <= ids
            if not step.any():
                break
            seg = seg + step
        else:  # very uneven segment lengths: fall back to the binary search
            seg = np.searchsorted(self.cum, ids, side="right") - 1
        return seg, self.start[seg] + (ids - self.cum[seg]) * self.stride


class DatasetView:
    """Gathers observations (stacking frames where the schema says so) for global steps."""

    def __init__(self, ds: Dataset):
        self.ds = ds
        self.schema = ds.schema
        self.length = np.asarray(ds.length, np.int64)
        self.start = np.asarray(ds.start, np.int64)
        self.last = self.start + self.length - 1
        self.frame_start = np.asarray(ds.frame_start, np.int64)

    def observation(self, seg: np.ndarray, steps: np.ndarray) -> np.ndarray | dict[str, np.ndarray]:
        """Observations at global ``steps`` (any shape) lying in segments ``seg`` (same shape)."""
        if self.schema.frame_stack > 1:
            first = self.frame_start[seg] + (steps - self.start[seg])  # frame row of step - k + 1
            out = stack_frames(self.ds.column("observation"), first, self.schema.frame_stack)
            self.ds.release_pages("observation")
            return out
        if not isinstance(self.schema.observation, ArraySpec):
            parts: dict[str, np.ndarray] = {}
            for key in self.schema.observation:
                parts[key] = _take(self.ds.column(f"observation/{key}"), steps)
                self.ds.release_pages(f"observation/{key}")
            return parts
        out = _take(self.ds.column("observation"), steps)
        self.ds.release_pages("observation")
        return out

    def stacked_pair(
        self, seg: np.ndarray, steps: np.ndarray, next_steps: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Frame stacks at ``steps`` and at ``next_steps`` (same segments, d = next - step >= 1
        steps later) from one gather of k + d frames per row instead of 2k: the two stacks
        overlap in k - d frames (all but one for 1-step transitions)."""
        k = self.schema.frame_stack
        gap = next_steps - steps
        first = self.frame_start[seg] + (steps - self.start[seg])  # frame row of step - k + 1
        span = k + int(gap.max(initial=1))
        # rows past a row's own next stack are never read; clamp them onto its newest frame so
        # the gather stays inside the segment's frames
        rows = np.minimum(first[:, None] + np.arange(span), (first + gap + k - 1)[:, None])
        frames = _take(self.ds.column("observation"), rows)  # (B, span, H, W)
        self.ds.release_pages("observation")
        current = frames[:, :k]
        if int(gap.min(initial=1)) == int(gap.max(initial=1)):
            later = frames[:, int(gap.max(initial=1)) :][:, :k]
        else:
            later = frames[np.arange(len(gap))[:, None], gap[:, None] + np.arange(k)]
        return np.moveaxis(current, 1, -1), np.moveaxis(later, 1, -1)

    def column(self, name: str, steps: np.ndarray) -> np.ndarray:
        # step columns (action, reward, discount, flags) are always raw arrays: see _take
        return np.take(self.ds.column(name), steps, axis=0)


# --- SARSA transitions ----------------------------------------------------------------------
class TransitionView(DatasetView):
    """The paper's SARSA tuples ``(s, a, r, discount, s', a')``, optionally n-step."""

    def __init__(
        self, ds: Dataset, n_step: int = 1, gamma: float = 1.0, reward_clip: float | None = None
    ):
        super().__init__(ds)
        if n_step < 1:
            raise RluError(f"n_step={n_step}; use 1 or more")
        self.n_step, self.gamma = int(n_step), float(gamma)
        self.reward_clip = None if reward_clip is None else float(reward_clip)
        terminal_end = np.asarray(ds.column("is_terminal"))[self.last] if self.n_step > 1 else None
        self.index = _Index(ds, n_step_counts(self.length, terminal_end, self.n_step))

    def __len__(self) -> int:
        return self.index.size

    def batch(self, ids: np.ndarray) -> Transition:
        """The transitions with index ``ids`` (n-step rewards and discounts, next observations and
        actions) as one ``Transition`` batch."""
        seg, t = self.index.locate(ids)
        reward, discount, nxt = n_step_targets(
            self.ds.column("reward"),
            self.ds.column("discount"),
            t,
            self.last[seg],
            self.n_step,
            self.gamma,
            self.reward_clip,
        )
        observation: Observation
        next_observation: Observation
        if self.schema.frame_stack > 1:
            observation, next_observation = self.stacked_pair(seg, t, nxt)
        else:
            observation, next_observation = self.observation(seg, t), self.observation(seg, nxt)
        return Transition(
            observation=observation,
            action=self.column("action", t),
            reward=reward,
            discount=discount,
            next_observation=next_observation,
            next_action=self.column("action", nxt),
        )

    def all(self) -> Transition:
        """Every transition of the view, in order, as one batch."""
        return self.batch(np.arange(len(self)))


# --- sequences ------------------------------------------------------------------------------
class SequenceView(DatasetView):
    """Fixed-length windows with a padding mask (recurrent agents, the seq-40 tasks)."""

    def __init__(
        self,
        ds: Dataset,
        length: int,
        stride: int = 1,
        return_to_go: bool = False,
        timestep: bool = False,
    ):
        super().__init__(ds)
        self.timestep = bool(timestep)
        if length < 1 or stride < 1:
            raise RluError(f"sequence length={length}, stride={stride}; both must be >= 1")
        self.seq_length, self.stride = int(length), int(stride)
        self.rtg_cum: np.ndarray | None = None
        if return_to_go:  # running sum of the rewards: 8 bytes a step, built once per view
            self.rtg_cum = np.concatenate([[0.0], np.cumsum(ds.column("reward"), dtype=np.float64)])
        # windows start at step 0, stride, 2*stride ... up to the last step that holds a
        # transition (a one-step segment still gives one window)
        counts = (np.maximum(self.length - 2, 0) // stride) + 1
        self.index = _Index(ds, counts, stride)

    def __len__(self) -> int:
        return self.index.size

    def batch(self, ids: np.ndarray) -> Sequence:
        """The windows with index ``ids`` as one ``Sequence`` batch (``mask`` marks the steps inside
        the segment)."""
        seg, t = self.index.locate(ids)
        steps = t[:, None] + np.arange(self.seq_length)
        mask = steps <= self.last[seg][:, None]
        steps = np.minimum(steps, self.last[seg][:, None])
        segs = np.broadcast_to(seg[:, None], steps.shape)

        def padded(x: np.ndarray) -> np.ndarray:
            m = mask.reshape(mask.shape + (1,) * (x.ndim - 2))
            return np.where(m, x, np.zeros((), x.dtype))

        obs = self.observation(segs, steps)
        obs = {k: padded(v) for k, v in obs.items()} if isinstance(obs, dict) else padded(obs)
        rtg = None
        if self.rtg_cum is not None:  # sum of rewards t .. last of the segment
            rtg = self.rtg_cum[(self.last[seg] + 1)[:, None]] - self.rtg_cum[steps]
            rtg = np.where(mask, rtg, 0.0).astype(np.float32)
        ts = np.where(mask, steps - self.start[seg][:, None], 0) if self.timestep else None
        return Sequence(
            observation=obs,
            action=padded(self.column("action", steps)),
            reward=padded(self.column("reward", steps)),
            discount=padded(self.column("discount", steps)),
            is_first=padded(self.column("is_first", steps)),
            is_last=padded(self.column("is_last", steps)),
            mask=mask,
            return_to_go=rtg,
            timestep=ts,
        )


# --- samplers -------------------------------------------------------------------------------
class Sampler:
    """Uniform random minibatches from a view, with an explicit seeded generator."""

    def __init__(self, view: TransitionView | SequenceView, batch_size: int, seed: int = 0):
        if len(view) == 0:
            raise RluError(f"{view.ds.path}: the dataset has no {type(view).__name__} samples: "
                           + _why_no_samples(view))  # fmt: skip
        self.view, self.batch_size = view, int(batch_size)
        self.rng = np.random.default_rng(seed)

    def sample(self) -> Transition | Sequence:
        """One batch of ``batch_size`` items drawn uniformly with replacement from the view."""
        return self.view.batch(self.rng.integers(0, len(self.view), size=self.batch_size))

    def __iter__(self) -> Iterator:
        while True:
            yield self.sample()

    def epoch(self, shuffle: bool = True, drop_last: bool = False) -> Iterator:
        """Every sample once, in batches (a permutation drawn from this sampler's generator)."""
        order = self.rng.permutation(len(self.view)) if shuffle else np.arange(len(self.view))
        stop = len(order) - (len(order) % self.batch_size if drop_last else 0)
        for i in range(0, stop, self.batch_size):
            yield self.view.batch(order[i : i + self.batch_size])

    def get_state(self) -> dict:
        """The sampler's generator state (for checkpoints)."""
        return {"bit_generator": self.rng.bit_generator.state}

    def set_state(self, state: dict) -> None:
        """Restore a generator state from :meth:`get_state`, so the batches go on as they would
        have."""
        self.rng.bit_generator.state = state["bit_generator"]


def _why_no_samples(view: TransitionView | SequenceView) -> str:
    """Why an empty view is empty, and the fix, for the sampler's error."""
    longest = int(view.length.max(initial=0))
    if longest < 2:
        held = "no segments" if not len(view.length) else "no segment of 2 or more steps"
        return f"it holds {held} (a transition needs two steps of one segment)"
    n = view.n_step if isinstance(view, TransitionView) else 1
    return (
        f"a {n}-step transition needs {n + 1} steps of one segment (or a terminal inside its "
        f"window) and the longest segment holds {longest} (window files convert to one segment "
        "per window: 2 steps for dm_control_suite, dm_locomotion seq2 and bsuite); use "
        f"n_step <= {longest - 1} (an agent override, e.g. `rlu train ... n_step={longest - 1}`)"
        " or a family that keeps whole episodes (dm_control_suite_episodes, "
        "dm_locomotion_episodes, atari_episodes_ordered)"
    )


def transition_sampler(
    ds: Dataset,
    batch_size: int,
    seed: int = 0,
    n_step: int = 1,
    gamma: float = 1.0,
    reward_clip: float | None = None,
) -> Sampler:
    """A sampler of ``Transition`` batches of ``batch_size`` from ``ds`` (``n_step`` returns
    discounted by ``gamma``, rewards clipped to ``reward_clip``), seeded with ``seed``:
    ``transition_sampler(ds, 256, seed=0).sample()``."""
    return Sampler(TransitionView(ds, n_step, gamma, reward_clip), batch_size, seed)


def sequence_sampler(
    ds: Dataset, batch_size: int, length: int, seed: int = 0, stride: int = 1
) -> Sampler:
    """A sampler of ``Sequence`` batches: ``batch_size`` windows of ``length`` steps (starting every
    ``stride`` steps), seeded with ``seed``."""
    return Sampler(SequenceView(ds, length, stride), batch_size, seed)


def make_view(
    dataset: str | os.PathLike | Dataset, spec: BatchSpec
) -> TransitionView | SequenceView:
    """The view a :class:`rlu.types.BatchSpec` asks for, over a dataset or its path."""
    ds = open_dataset(dataset) if isinstance(dataset, str | os.PathLike) else dataset
    if spec.kind == "sequence":
        if spec.reward_clip is not None:
            raise RluError(
                "BatchSpec.reward_clip is applied by transition batches only; clip sequence "
                "rewards in the agent"
            )
        return SequenceView(
            ds, spec.sequence_length, return_to_go=spec.return_to_go, timestep=spec.timestep
        )
    return TransitionView(ds, spec.n_step, spec.gamma, spec.reward_clip)


def make_sampler(dataset: str | os.PathLike | Dataset, spec: BatchSpec, seed: int = 0) -> Sampler:
    """Uniform batches of what ``spec`` (an agent's ``batch_spec``) asks for."""
    if not isinstance(spec, BatchSpec):
        raise RluError(
            f"make_sampler takes a rlu.types.BatchSpec, got {type(spec).__name__}; build one "
            "with BatchSpec(batch_size, kind, n_step, gamma, sequence_length) or pass "
            "agent.batch_spec"
        )
    return Sampler(make_view(dataset, spec), spec.batch_size, seed)
