"""Per-family decoding of the release into loader-shaped arrays and into Segments, and back.

Two views of each record (docs/release_format.md §3, §4):

- ``parse``: the arrays the original loaders return (``dm_control_suite.py``'s parsed sequences,
  ``atari.py``'s tuple, ...): time-first float32 arrays, PNGs decoded, ids bitcast. ``encode`` is
  its inverse: it writes a record in the exact release schema (our writer for round trips).
- ``segments``: the same data in rlu's model (:class:`rlu.data.episode.Segment`, RLDS steps). Each
  family's alignment rule, pinned by one test each in ``tests/release/test_families.py``:

  ```text
  ============================  ==============================================================
  family                        reward_t / discount_t / final step
  ============================  ==============================================================
  atari (transitions)           2 steps (o_t, o_tp1 stacks); reward_0 = r_t, discount_0 = d_t;
                                d_t == 0 marks step 1 is_last + is_terminal; step 1's reward 0.
                                r_t is the clipped reward (the only one these files hold); the
                                file's clipped episode return goes to clipped_episode_return
  atari_episodes_ordered        rewards unshifted, the raw game score (unclipped_rewards; the
                                file's clipped_rewards must equal clip(raw, -1, 1), checked); if
                                the last discount is 0 the episode is terminal and discounts
                                shift left with a 0 appended (TFDS ``atari_utils``); frames
                                stored once, stack 4 at sample time
  dm_control_suite, dm_locomotion windows (seq2 / seq40): values as stored; reward_t = reward[t],
                                discount_t = discount[t] (the loader's r_t = reward[0], p_t =
                                discount[0]); is_first / is_last from step_type (FIRST 0, LAST 2);
                                a LAST step with discount 0 is terminal
  *_episodes                    "RSA" files: reward_t = reward[t+1], discount_t = discount[t+1],
                                actions unshifted; terminal when the last discount is 0, and
                                the final step's discount 0 then, 1 at a time limit (TFDS)
  rwrl                          index 0 of action / reward / discount is a placeholder:
                                action_t = action[t+1] (last repeated), reward_t = reward[t+1],
                                discount_t = discount[t+1] (``rwrl.py``)
  bsuite                        2 steps; discount_0 = discount[0] * (step_type[1] != LAST), so
                                every LAST is terminal (the notebook's loader)
  dmlab                         fixed-length episodes, values as stored; pixels BGR -> RGB
  ============================  ==============================================================
  ```

Where a segment's last step carries values the file holds (windows), they are kept, so that the
transition view yields exactly the loader's ``(o_t, a_t, r_t, d_t, o_tp1, a_tp1)``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rlu.data.episode import Segment
from rlu.data.release import example as ex
from rlu.data.release.framing import RecordReader, RecordWriter
from rlu.data.release.png import decode_png, encode_png
from rlu.tasks import ATARI_MAX_AGENT_STEPS
from rlu.types import FormatError

FIRST, MID, LAST = 0, 1, 2
CAMERA_KEY = "observation/walker/egocentric_camera"
CAMERA_SHAPE = (64, 64, 3)
ATARI_FRAME = (84, 84)
DMLAB_FRAME = (72, 96, 3)
_WINDOW_SCALARS = ("reward", "discount", "step_type", "episodic_reward")
Raw = dict[str, np.ndarray]


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


def _need(cols: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in cols:
        raise FormatError(f"{where}: feature {key!r} is missing; found {sorted(cols)}")
    return cols[key]


def _field(raw: Raw, key: str, lead: tuple[int, ...], ndim: int | None = None) -> np.ndarray:
    """``raw[key]``, which must be numeric, start with the ``lead`` dimensions (records, steps:
    each at least 1) and have ``ndim`` dimensions (None: any beyond ``lead``)."""
    if key not in raw:
        raise FormatError(f"feature {key!r} is missing; found {sorted(raw)}")
    v = np.asarray(raw[key])
    if v.dtype.kind not in "biuf":
        raise FormatError(f"feature {key!r} holds {v.dtype} values; a numeric list was expected")
    want = f"{len(lead) if ndim is None else ndim} dimensions starting {lead}"
    if v.shape[: len(lead)] != lead or (ndim is not None and v.ndim != ndim) or v.ndim < len(lead):
        raise FormatError(f"feature {key!r} has shape {v.shape}; the family holds {want}")
    if 0 in lead or (v.ndim > len(lead) and 0 in v.shape[len(lead) :]):
        raise FormatError(f"feature {key!r} has shape {v.shape}: an empty list")
    return v


def _steps(raw: Raw, key: str) -> tuple[int, int]:
    """(records, steps) of the time-major scalar feature ``key``, at least one of each."""
    v = _field(raw, key, (), 2)
    if v.shape[0] < 1 or v.shape[1] < 1:
        raise FormatError(f"feature {key!r} has shape {v.shape}: no steps")
    return v.shape


def _numeric(col: Any, key: str, where: str) -> np.ndarray:
    if isinstance(col, ex.BytesColumn):
        raise FormatError(f"{where}: feature {key!r} is a bytes_list; a numeric list was expected")
    if col.dtype == object:
        raise FormatError(f"{where}: feature {key!r} has different lengths across records")
    return col


def _scalar(
    cols: Mapping[str, Any],
    key: str,
    where: str,
    dtype: type[np.generic] | None = None,
    integer: bool = False,
) -> np.ndarray:
    v = _numeric(_need(cols, key, where), key, where)
    if integer:
        _integers(v, key, where)
    if v.ndim != 2 or v.shape[1] != 1:
        raise FormatError(f"{where}: feature {key!r} must hold one value, it holds {v.shape[1:]}")
    v = v[:, 0]
    return v.astype(dtype) if dtype is not None else v


def _integers(v: np.ndarray, key: str, where: str) -> np.ndarray:
    """``v``, which the release stores as an int64_list (actions, ids, indices)."""
    if v.dtype != np.int64:
        raise FormatError(
            f"{where}: feature {key!r} is a float_list; the release stores it as an int64_list"
        )
    return v


def _time_major(v: np.ndarray, t: int, key: str, where: str, scalar: bool) -> np.ndarray:
    n, count = v.shape
    if t == 0 or count % t:
        raise FormatError(f"{where}: feature {key!r} holds {count} values, not a multiple of T={t}")
    return v.reshape(n, t) if scalar and count == t else v.reshape(n, t, count // t)


def _split_rows(cols: Mapping[str, Any], n: int) -> list[dict[str, Any]]:
    """Columns of a batch with ragged lists -> one single-record column dict per record."""
    rows: list[dict[str, Any]] = [{} for _ in range(n)]
    for k, c in cols.items():
        for i in range(n):
            if isinstance(c, ex.BytesColumn):
                rows[i][k] = ex.BytesColumn(values=[c.values[i]])
            elif c.dtype == object:
                rows[i][k] = c[i][None, :]
            else:
                rows[i][k] = c[i : i + 1]
    return rows


def _ragged(cols: Mapping[str, Any]) -> bool:
    return any(not isinstance(c, ex.BytesColumn) and c.dtype == object for c in cols.values())


def _png_stack(
    col: ex.BytesColumn,
    count: int | None,
    key: str,
    where: str,
    channels: int,
    size: tuple[int, int],
) -> list[list[np.ndarray]]:
    vals = col.values
    if count is not None and any(len(v) != count for v in vals):
        raise FormatError(f"{where}: {key!r} must hold {count} PNG frames per record")
    try:
        return [[decode_png(f, channels, size) for f in v] for v in vals]
    except FormatError as e:
        raise FormatError(f"{where}: {key!r}: {e}") from None


# --- control suite / locomotion windows and episodes ----------------------------------------


def parse_sequences(cols: Mapping[str, Any], where: str = "record") -> list[Raw]:
    """``dm_control_suite.py``'s parse: every list reshaped (T, ...) time first; camera raw uint8.

    Returns one stacked dict per run of records of equal T (usually one for a whole batch).
    """
    if not cols:
        return []
    n = len(next(iter(cols.values())))
    if _ragged(cols):
        return [b for row in _split_rows(cols, n) for b in parse_sequences(row, where)]
    t = _numeric(_need(cols, "discount", where), "discount", where).shape[1]
    out: Raw = {}
    for k, c in cols.items():
        if isinstance(c, ex.BytesColumn):
            if k != CAMERA_KEY:
                continue  # no bytes feature but the camera is named by the loaders
            flat = c.concatenated()
            per_step = int(np.prod(CAMERA_SHAPE))
            if flat.shape[1] != t * per_step:
                raise FormatError(
                    f"{where}: {k!r} holds {flat.shape[1]} bytes per record; T={t} steps of "
                    f"64x64x3 need {t * per_step}"
                )
            out[k] = flat.reshape(n, t, *CAMERA_SHAPE)
        elif c.dtype == np.int64 and k in ("episode_id", "timestamp"):
            out[k] = c[:, 0] if c.shape[1] == 1 else c
        else:
            out[k] = _time_major(c, t, k, where, scalar=k in _WINDOW_SCALARS)
    out["length"] = np.full(n, t, np.int32)
    return [out]


def _observation(raw: Raw, prefix: str = "observation/") -> dict[str, np.ndarray]:
    obs = {k[len(prefix) :]: v for k, v in raw.items() if k.startswith(prefix)}
    if not obs:
        raise FormatError(f"no {prefix}* features in the record; found {sorted(raw)}")
    return obs


def window_segments(raw: Raw) -> SegmentBatch:
    """Release windows (seq2 / seq40) -> segments with the loader's alignment.

    A window ends at its first LAST step: anything after it is padding (Acme's sequence adder
    pads with zero steps, whose step_type 0 would read as FIRST) and is dropped. The final step
    is terminal when the transition into it has discount 0 (the loader's ``p_t``); the LAST
    step's own stored discount reaches no transition.
    """
    n, t = _steps(raw, "discount")
    step_type = _field(raw, "step_type", (n, t), 2)
    discount = raw["discount"].astype(np.float32)
    _field(raw, "reward", (n, t), 2)
    _field(raw, "action", (n, t), 3)
    obs = {k: _field(raw, f"observation/{k}", (n, t)) for k in _observation(raw)}
    is_last = step_type == LAST
    is_first = step_type == FIRST
    # cut after the first LAST, and before a FIRST that is not step 0 (a new episode)
    ends = np.full(n, t)
    has_last = is_last.any(axis=1)
    ends[has_last] = np.argmax(is_last[has_last], axis=1) + 1
    late_first = is_first.copy()
    late_first[:, 0] = False
    has_late = late_first.any(axis=1)
    ends[has_late] = np.minimum(ends[has_late], np.argmax(late_first[has_late], axis=1))
    if (ends < 1).any():
        raise FormatError("a window has no steps before its episode boundary")
    steps = np.arange(t)
    inside = steps[None, :] < ends[:, None]
    is_last = is_last & inside
    is_first = is_first & inside
    prev_discount = np.ones_like(discount)
    prev_discount[:, 1:] = discount[:, :-1]
    is_terminal = is_last & (prev_discount == 0) & (steps[None, :] > 0)
    return SegmentBatch(
        observation=obs,
        action=raw["action"],
        reward=raw["reward"].astype(np.float32),
        discount=discount,
        is_first=is_first,
        is_last=is_last,
        is_terminal=is_terminal,
        lengths=None if (ends == t).all() else ends,
    )


def episode_segments(raw: Raw) -> SegmentBatch:
    """``*_episodes`` files ("RSA"): reward and discount move one step earlier (TFDS)."""
    n, t = _steps(raw, "reward")
    reward = raw["reward"].astype(np.float32)
    discount = _field(raw, "discount", (n, t), 2).astype(np.float32)
    _field(raw, "action", (n, t), 3)
    obs = {k: _field(raw, f"observation/{k}", (n, t)) for k in _observation(raw)}
    terminal = discount[:, -1] == 0
    r = np.zeros_like(reward)
    r[:, :-1] = reward[:, 1:]
    d = np.zeros_like(discount)
    d[:, :-1] = discount[:, 1:]
    d[:, -1] = np.where(terminal, 0.0, 1.0)  # TFDS: 0 appended at a terminal end, else 1
    flags = np.zeros((n, t), bool)
    is_first, is_last, is_terminal = flags.copy(), flags.copy(), flags.copy()
    is_first[:, 0] = True
    is_last[:, -1] = True
    is_terminal[:, -1] = terminal
    meta = {"episode_return": r.sum(axis=1, dtype=np.float64)}
    if "episode_id" in raw:
        ids = _field(raw, "episode_id", (n,), 1)
        if ids.dtype != np.int64:
            raise FormatError(f"feature 'episode_id' holds {ids.dtype}; an int64 list")
        meta["episode_id"] = ids.view(np.uint64)
    return SegmentBatch(obs, raw["action"], r, d, is_first, is_last, is_terminal, meta)


def encode_sequence(rec: Mapping[str, np.ndarray]) -> bytes:
    """One window / episode record (loader-shaped, T first) -> release Example bytes."""
    feats: dict[str, Any] = {}
    kinds: dict[str, int] = {}
    for k, v in rec.items():
        if k == "length":
            continue
        v = np.asarray(v)
        if k == CAMERA_KEY:
            feats[k] = [np.ascontiguousarray(v, np.uint8).tobytes()]
        elif k in ("episode_id", "timestamp"):
            feats[k] = v.reshape(-1).view(np.int64) if v.dtype == np.uint64 else v.reshape(-1)
            kinds[k] = ex.INT64
        else:
            feats[k] = v.astype(np.float32).reshape(-1)  # step_type is stored as float
            kinds[k] = ex.FLOAT
    return ex.encode_example(feats, kinds=kinds)


# --- Atari ---------------------------------------------------------------------------------


def parse_atari_transitions(cols: Mapping[str, Any], where: str = "record") -> list[Raw]:
    """``atari.py``: four PNGs per observation stacked as channels; ids bitcast to uint64."""
    out: Raw = {}
    for k in ("o_t", "o_tp1"):
        col = _need(cols, k, where)
        if not isinstance(col, ex.BytesColumn):
            raise FormatError(f"{where}: {k!r} must be a bytes_list of 4 PNG frames")
        frames = _png_stack(col, 4, k, where, channels=1, size=ATARI_FRAME)
        arr = np.asarray(frames, np.uint8)
        if arr.ndim != 4 or arr.shape[2:] != ATARI_FRAME:
            raise FormatError(f"{where}: {k!r} frames must be 84x84 grey, got {arr.shape[2:]}")
        out[k] = np.ascontiguousarray(arr.transpose(0, 2, 3, 1))
    out["a_t"] = _scalar(cols, "a_t", where, np.int32, integer=True)
    out["a_tp1"] = _scalar(cols, "a_tp1", where, np.int32, integer=True)
    out["r_t"] = _scalar(cols, "r_t", where, np.float32)
    out["d_t"] = _scalar(cols, "d_t", where, np.float32)
    out["episode_id"] = _scalar(cols, "episode_id", where, integer=True).view(np.uint64)
    out["episode_return"] = _scalar(cols, "episode_return", where, np.float32)
    return [out]


def atari_transition_segments(raw: Raw) -> SegmentBatch:
    n = raw["r_t"].shape[0]
    terminal = raw["d_t"] == 0
    reward = np.zeros((n, 2), np.float32)
    reward[:, 0] = raw["r_t"]
    discount = np.ones((n, 2), np.float32)
    discount[:, 0] = raw["d_t"]
    discount[:, 1] = np.where(terminal, 0.0, 1.0)
    is_last = np.zeros((n, 2), bool)
    is_last[:, 1] = terminal
    return SegmentBatch(
        observation=np.stack([raw["o_t"], raw["o_tp1"]], axis=1),
        action=np.stack([raw["a_t"], raw["a_tp1"]], axis=1).astype(np.int64),
        reward=reward,
        discount=discount,
        is_first=np.zeros((n, 2), bool),
        is_last=is_last,
        is_terminal=is_last.copy(),
        metadata={
            "episode_id": raw["episode_id"],
            # atari.py: "Total episode return computed using per-step [-1, 1] clipping". The
            # raw game score is not in these files, so episode_return stays missing.
            "clipped_episode_return": raw["episode_return"].astype(np.float64),
        },
    )


def encode_atari_transition(rec: Mapping[str, np.ndarray]) -> bytes:
    feats = {
        "o_t": [encode_png(rec["o_t"][..., k]) for k in range(rec["o_t"].shape[-1])],
        "o_tp1": [encode_png(rec["o_tp1"][..., k]) for k in range(rec["o_tp1"].shape[-1])],
        "a_t": np.asarray([rec["a_t"]], np.int64),
        "a_tp1": np.asarray([rec["a_tp1"]], np.int64),
        "r_t": np.asarray([rec["r_t"]], np.float32),
        "d_t": np.asarray([rec["d_t"]], np.float32),
        "episode_id": np.asarray([rec["episode_id"]], np.uint64).view(np.int64),
        "episode_return": np.asarray([rec["episode_return"]], np.float32),
    }
    return ex.encode_example(feats)


_ATARI_EP_LISTS = ("actions", "unclipped_rewards", "clipped_rewards", "discounts")
_ATARI_EP_SCALARS = ("checkpoint_idx", "episode_idx", "episode_return", "clipped_episode_return")


def parse_atari_episodes(cols: Mapping[str, Any], where: str = "record") -> list[Raw]:
    """``atari_episodes_ordered``: one episode per record, T single 84x84 PNG frames."""
    n = len(next(iter(cols.values()))) if cols else 0
    out = []
    for row in _split_rows(cols, n) if n > 1 else [cols]:
        col = _need(row, "observations", where)
        if not isinstance(col, ex.BytesColumn):
            raise FormatError(f"{where}: 'observations' must be a bytes_list of PNG frames")
        t = _integers(_numeric(_need(row, "actions", where), "actions", where), "actions", where)
        t = t.shape[1]
        if t > ATARI_MAX_AGENT_STEPS + 1:
            # checked before a frame is decoded: 100 MB of tiny PNGs would inflate to gigabytes
            raise FormatError(
                f"{where}: an episode of {t:,} steps; the recording stopped episodes at "
                f"{ATARI_MAX_AGENT_STEPS:,} agent steps (108,000 frames)"
            )
        rec: Raw = {}
        for k in _ATARI_EP_LISTS:
            v = _numeric(_need(row, k, where), k, where)
            if v.shape[1] != t:
                raise FormatError(f"{where}: {k!r} has {v.shape[1]} steps, 'actions' has {t}")
            rec[k] = v[0]
        frames = _png_stack(col, t, "observations", where, channels=1, size=ATARI_FRAME)[0]
        rec["observations"] = np.asarray(frames, np.uint8).reshape(t, *ATARI_FRAME)
        for k in _ATARI_EP_SCALARS:
            rec[k] = _scalar(row, k, where, integer=k.endswith("_idx"))[0]
        out.append({k: np.asarray(v)[None] for k, v in rec.items()})
    return out


def atari_episode_segment(raw: Raw) -> SegmentBatch:
    (n, t) = raw["actions"].shape
    # rlu stores the raw reward and derives the clipped one as clip(r, -1, 1) (what Dopamine's
    # runner stores and the agents learn from); a file whose clipped_rewards say otherwise
    # would make that derived reward wrong, so it is refused rather than silently changed.
    raw_r = raw["unclipped_rewards"].astype(np.float32)
    bad = np.argwhere(np.clip(raw_r, -1, 1) != raw["clipped_rewards"].astype(np.float32))
    if bad.size:
        i, j = (int(x) for x in bad[0])
        raise FormatError(
            f"atari_episodes_ordered episode {i} step {j}: clipped_rewards holds "
            f"{float(raw['clipped_rewards'][i, j])} but clip(unclipped_rewards, -1, 1) is "
            f"{float(np.clip(raw_r[i, j], -1, 1))}; rlu keeps the raw reward and derives the "
            "clipped one, so it cannot store this file faithfully (is the file damaged?)"
        )
    disc = raw["discounts"].astype(np.float32)
    terminal = disc[:, -1] == 0
    discount = disc.copy()
    discount[terminal, :-1] = disc[terminal, 1:]
    discount[terminal, -1] = 0.0
    flags = np.zeros((n, t), bool)
    is_first, is_last, is_terminal = flags.copy(), flags.copy(), flags.copy()
    is_first[:, 0] = True
    is_last[:, -1] = True
    is_terminal[:, -1] = terminal
    ckpt = raw["checkpoint_idx"].astype(np.int64)
    ep = raw["episode_idx"].astype(np.int64)
    return SegmentBatch(
        observation=raw["observations"],
        action=raw["actions"].astype(np.int64),
        reward=raw_r,
        discount=discount,
        is_first=is_first,
        is_last=is_last,
        is_terminal=is_terminal,
        metadata={
            # the ordered TFDS builder's key: checkpoint * 1e10 + episode
            "episode_id": (ckpt * 10**10 + ep).astype(np.uint64),
            "checkpoint": ckpt,
            "episode_index": ep,
            "episode_return": raw["episode_return"].astype(np.float64),
            "clipped_episode_return": raw["clipped_episode_return"].astype(np.float64),
        },
    )


def encode_atari_episode(rec: Mapping[str, np.ndarray]) -> bytes:
    feats: dict[str, Any] = {"observations": [encode_png(f) for f in rec["observations"]]}
    feats["actions"] = np.asarray(rec["actions"], np.int64)
    for k in ("unclipped_rewards", "clipped_rewards", "discounts"):
        feats[k] = np.asarray(rec[k], np.float32)
    feats["checkpoint_idx"] = np.asarray([rec["checkpoint_idx"]], np.int64)
    feats["episode_idx"] = np.asarray([rec["episode_idx"]], np.int64)
    feats["episode_return"] = np.asarray([rec["episode_return"]], np.float32)
    feats["clipped_episode_return"] = np.asarray([rec["clipped_episode_return"]], np.float32)
    return ex.encode_example(feats)


# --- RWRL ----------------------------------------------------------------------------------


def parse_rwrl(cols: Mapping[str, Any], where: str = "record") -> list[Raw]:
    """``rwrl.py``: flat float lists of T (1001) steps; keys nest with ':'."""
    n = len(next(iter(cols.values()))) if cols else 0
    if n == 0:
        return []
    if _ragged(cols):
        return [b for row in _split_rows(cols, n) for b in parse_rwrl(row, where)]
    t = _numeric(_need(cols, "reward", where), "reward", where).shape[1]
    out: Raw = {}
    for k, c in cols.items():
        c = _numeric(c, k, where)
        out[k] = _time_major(c, t, k, where, scalar=False)
    return [out]


def rwrl_segments(raw: Raw) -> SegmentBatch:
    obs = {
        k[len("observation:") :].replace(":", "/"): v
        for k, v in raw.items()
        if k.startswith("observation:")
    }
    if not obs:
        raise FormatError(f"RWRL record has no observation:* features; found {sorted(raw)}")
    n, t = _field(raw, "reward", (), 3).shape[:2]
    if n < 1 or t < 1:
        raise FormatError(f"feature 'reward' has shape {raw['reward'].shape}: no steps")
    for k in ("reward", "discount"):
        if _field(raw, k, (n, t), 3).shape[2] != 1:
            raise FormatError(f"feature {k!r} holds {raw[k].shape[2]} values per step; want 1")
    obs = {k: _field({k: v}, k, (n, t)) for k, v in obs.items()}
    action = _field(raw, "action", (n, t), 3)
    reward = raw["reward"][..., 0].astype(np.float32)
    disc = raw["discount"][..., 0].astype(np.float32)
    act = np.concatenate([action[:, 1:], action[:, -1:]], axis=1)  # index 0 is a placeholder
    r = np.zeros_like(reward)
    r[:, :-1] = reward[:, 1:]
    d = np.zeros_like(disc)
    d[:, :-1] = disc[:, 1:]
    flags = np.zeros((n, t), bool)
    is_first, is_last, is_terminal = flags.copy(), flags.copy(), flags.copy()
    is_first[:, 0] = True
    is_last[:, -1] = True
    is_terminal[:, -1] = disc[:, -1] == 0
    meta = {"episode_return": r.sum(axis=1, dtype=np.float64)}
    return SegmentBatch(obs, act, r, d, is_first, is_last, is_terminal, meta)


def encode_rwrl(rec: Mapping[str, np.ndarray]) -> bytes:
    return ex.encode_example({k: np.asarray(v, np.float32).reshape(-1) for k, v in rec.items()})


# --- bsuite --------------------------------------------------------------------------------


def parse_bsuite(cols: Mapping[str, Any], where: str = "record") -> list[Raw]:
    n = len(next(iter(cols.values()))) if cols else 0
    if n == 0:
        return []
    if _ragged(cols):
        return [b for row in _split_rows(cols, n) for b in parse_bsuite(row, where)]
    t = _numeric(_need(cols, "reward", where), "reward", where).shape[1]
    out: Raw = {}
    for k, c in cols.items():
        c = _numeric(c, k, where)
        if k in ("action", "step_type"):
            _integers(c, k, where)
        out[k] = _time_major(c, t, k, where, scalar=k != "observation")
    return [out]


def bsuite_segments(raw: Raw) -> SegmentBatch:
    n, t = _steps(raw, "step_type")
    st = raw["step_type"]
    for k in ("discount", "reward", "action"):
        _field(raw, k, (n, t), 2)
    _field(raw, "observation", (n, t), 3)
    discount = raw["discount"].astype(np.float32).copy()
    # the notebook's loader: gamma = discount[0] * (step_type[1] != LAST)
    discount[:, :-1] *= (st[:, 1:] != LAST).astype(np.float32)
    is_last = st == LAST
    return SegmentBatch(
        observation=raw["observation"].astype(np.float32),
        action=raw["action"].astype(np.int64),
        reward=raw["reward"].astype(np.float32),
        discount=discount,
        is_first=st == FIRST,
        is_last=is_last,
        is_terminal=is_last.copy(),
    )


def encode_bsuite(rec: Mapping[str, np.ndarray]) -> bytes:
    feats = {k: np.asarray(v).reshape(-1) for k, v in rec.items() if k != "length"}
    kinds = {k: ex.INT64 if k in ("action", "step_type") else ex.FLOAT for k in feats}
    return ex.encode_example(feats, kinds=kinds)


# --- DMLab ---------------------------------------------------------------------------------

_DMLAB_LISTS = ("actions", "rewards", "discounts", "discounted_rewards", "observations_reward")


def parse_dmlab(cols: Mapping[str, Any], where: str = "record") -> list[Raw]:
    """DMLab episodes: T PNG frames 72x96x3 returned in the stored BGR order (as the notebook)."""
    n = len(next(iter(cols.values()))) if cols else 0
    out = []
    for row in _split_rows(cols, n) if n > 1 else [cols]:
        t = _integers(_numeric(_need(row, "actions", where), "actions", where), "actions", where)
        t = t.shape[1]
        if t < 1:
            raise FormatError(f"{where}: 'actions' is empty; an episode has at least one step")
        rec: Raw = {}
        for k in _DMLAB_LISTS:
            if k in row:
                v = _numeric(row[k], k, where)[0]
                if v.size != t:
                    raise FormatError(f"{where}: {k!r} holds {v.size} values, 'actions' {t}")
                rec[k] = v.reshape(t)
        last_action = _numeric(
            _need(row, "observations_action", where), "observations_action", where
        )[0]
        if last_action.size == 0 or last_action.size % t:
            raise FormatError(
                f"{where}: 'observations_action' holds {last_action.size} values, not a "
                f"multiple of the {t} steps"
            )
        rec["observations_action"] = last_action.reshape(t, -1)
        col = _need(row, "observations_pixels", where)
        if not isinstance(col, ex.BytesColumn):
            raise FormatError(f"{where}: 'observations_pixels' must be a bytes_list of PNGs")
        frames = _png_stack(col, t, "observations_pixels", where, 3, DMLAB_FRAME[:2])[0]
        rec["observations_pixels"] = np.asarray(frames, np.uint8).reshape(t, *DMLAB_FRAME)
        for k in ("episode_id", "start_idx", "episode_return"):
            if k in row:
                rec[k] = _scalar(row, k, where, integer=k != "episode_return")[0]
        out.append({k: np.asarray(v)[None] for k, v in rec.items()})
    return out


def dmlab_segment(raw: Raw) -> SegmentBatch:
    n, t = _steps(raw, "actions")
    for k in ("discounts", "rewards", "observations_reward"):
        _field(raw, k, (n, t), 2)
    disc = raw["discounts"].astype(np.float32)
    flags = np.zeros((n, t), bool)
    is_first, is_last, is_terminal = flags.copy(), flags.copy(), flags.copy()
    is_first[:, 0] = True
    is_last[:, -1] = True
    if t > 1:  # terminal when the transition into the final step has discount 0
        is_terminal[:, -1] = disc[:, -2] == 0
    meta: dict[str, np.ndarray] = {}
    if "episode_id" in raw:
        meta["episode_id"] = raw["episode_id"].astype(np.int64).view(np.uint64)
    if "episode_return" in raw:
        meta["episode_return"] = raw["episode_return"].astype(np.float64)
    return SegmentBatch(
        observation={
            "pixels": np.ascontiguousarray(raw["observations_pixels"][..., ::-1]),  # BGR -> RGB
            "last_action": raw["observations_action"].astype(np.float32),
            "last_reward": raw["observations_reward"].astype(np.float32),
        },
        action=raw["actions"].astype(np.int64),
        reward=raw["rewards"].astype(np.float32),
        discount=disc,
        is_first=is_first,
        is_last=is_last,
        is_terminal=is_terminal,
        metadata=meta,
    )


def encode_dmlab(rec: Mapping[str, np.ndarray]) -> bytes:
    feats: dict[str, Any] = {
        "observations_pixels": [encode_png(f) for f in rec["observations_pixels"]]
    }
    feats["actions"] = np.asarray(rec["actions"], np.int64)
    for k in ("rewards", "discounts", "discounted_rewards", "observations_reward"):
        feats[k] = np.asarray(rec[k], np.float32)
    feats["observations_action"] = np.asarray(rec["observations_action"], np.float32).reshape(-1)
    feats["episode_id"] = np.asarray([rec["episode_id"]], np.int64)
    feats["start_idx"] = np.asarray([rec["start_idx"]], np.int64)
    feats["episode_return"] = np.asarray([rec["episode_return"]], np.float32)
    return ex.encode_example(feats)


# --- the registry of families --------------------------------------------------------------


@dataclass(frozen=True)
class Family:
    name: str
    """The bucket's top folder."""
    compression: str | None
    parse: Callable[..., list[Raw]]
    segments: Callable[[Raw], SegmentBatch]
    encode: Callable[[Mapping[str, np.ndarray]], bytes]
    whole_episodes: bool
    """True when one record is one whole episode."""
    max_record_bytes: int
    """The longest record rlu reads in this family's files: a longer length header is damage or
    a bomb and is refused before any of the record is held (see ``record_note``)."""
    max_shard_bytes: int
    """The largest file a download of one of its shards may be: an endless body stops here."""
    record_note: str
    """What the family's records are, for the error that refuses a longer one."""


_MiB, _GiB = 1 << 20, 1 << 30
# Limits: well above what the release holds (sizes from the TFDS catalog, which describe the same
# data re-encoded; docs/release_format.md §5), well below what a machine cannot hold. Records: a
# window of 2 or 40 steps is a few kB (a locomotion seq40 window with its 64x64x3 camera, 0.5
# MB); a control-suite or RWRL episode is 1000 steps of at most ~90 floats (under 1 MB); a
# locomotion episode keeps 12,288 camera bytes per step (about 12-18 MB); an Atari episode up to
# 27,000 PNG frames (tens of MB); a DMLab episode of 72x96x3 PNG frames (3-14 MB on average).
# Shards: a control-suite task is at most 1.21 GiB in 100 shards, a locomotion task 23.1 GiB in
# 100, an Atari run about 75 GiB in 100 (or 50 episode shards), RWRL 6.78 GiB in 391, DMLab
# shards 145-265 MB.
FAMILIES: Mapping[str, Family] = {
    f.name: f
    for f in (
        Family("atari", "gzip", parse_atari_transitions, atari_transition_segments,
               encode_atari_transition, False, 4 * _MiB, 4 * _GiB,
               "an Atari transition is 8 PNG frames, tens of kB"),
        Family("atari_episodes_ordered", "gzip", parse_atari_episodes, atari_episode_segment,
               encode_atari_episode, True, 128 * _MiB, 8 * _GiB,
               "an Atari episode is at most 27,000 PNG frames, tens of MB"),
        Family("dm_control_suite", "gzip", parse_sequences, window_segments, encode_sequence,
               False, 4 * _MiB, 256 * _MiB, "a control-suite window of 2 steps is a few kB"),
        Family("dm_control_suite_episodes", "gzip", parse_sequences, episode_segments,
               encode_sequence, True, 16 * _MiB, 256 * _MiB,
               "a control-suite episode of 1000 steps is under 1 MB"),
        Family("dm_locomotion", "gzip", parse_sequences, window_segments, encode_sequence, False,
               16 * _MiB, 4 * _GiB, "a locomotion window of 2 or 40 steps is under 1 MB"),
        Family("dm_locomotion_episodes", "gzip", parse_sequences, episode_segments,
               encode_sequence, True, 128 * _MiB, 4 * _GiB,
               "a locomotion episode with its camera is about 12-18 MB"),
        Family("rwrl", None, parse_rwrl, rwrl_segments, encode_rwrl, True, 32 * _MiB, 1 * _GiB,
               "an RWRL episode of 1000 steps is under 1 MB"),
        Family("bsuite", "gzip", parse_bsuite, bsuite_segments, encode_bsuite, False, 4 * _MiB,
               1 * _GiB, "a bsuite transition is a few kB"),
        Family("dmlab", "gzip", parse_dmlab, dmlab_segment, encode_dmlab, True, 128 * _MiB,
               4 * _GiB, "a DMLab episode of 72x96 PNG frames is 3-14 MB on average"),
    )
}  # fmt: skip


def reader_for(path: str | os.PathLike, family: str, **kw: Any) -> RecordReader:
    """A :class:`RecordReader` of one of ``family``'s files, with the family's record limit."""
    fam = get_family(family)
    note = f"{fam.record_note}; a longer one is damage or a bomb, not a {fam.name} record"
    return RecordReader(path, max_record_bytes=fam.max_record_bytes, limit_note=note, **kw)


def get_family(name: str) -> Family:
    try:
        return FAMILIES[name]
    except KeyError:
        raise FormatError(
            f"unknown release family {name!r}; use one of {', '.join(FAMILIES)}"
        ) from None


def _batch_size(fam: Family) -> int:
    if fam.whole_episodes and fam.name in ("atari_episodes_ordered", "dmlab"):
        # an episode of frames decodes to ~28x its PNG bytes (a Pong frame: 250 B -> 7 kB), so
        # 64 of them held ~750 MB (bench/cluster.py); 4 bound a conversion job at ~1/16 of that
        # and decode as fast (a record is hundreds to thousands of frames)
        return 4
    return 64 if fam.name == "atari" else 4096


# Records of one decode batch, in bytes: a batch is decoded as soon as it holds this much, so a
# shard of long records (whole episodes, or a bomb of 100 MB records) costs one batch of memory
# at a time, never the shard. Batches only group the work: the output is the same for any size.
_BATCH_BYTES = 64 << 20


# What a record that passed its CRC but is not what its family holds makes numpy and the parsers
# raise (an empty list where one value is due, lists of the wrong length...); each becomes a
# FormatError naming the record.
_MALFORMED = (
    FormatError,
    ValueError,
    IndexError,
    TypeError,
    KeyError,
    AssertionError,
    OverflowError,
    RecursionError,
    ZeroDivisionError,
    AttributeError,
)


def _decode(fam: Family, recs: list[bytes], where: str, segments: bool) -> list[Any]:
    out = fam.parse(ex.decode_batch(recs), where)
    return [fam.segments(raw) for raw in out] if segments else out


def _read(
    fam: Family, rd: RecordReader, segments: bool, skip: bool
) -> Iterator[Raw | SegmentBatch]:
    """Decode, parse (and cut into segments) one shard's records in batches, in order.

    A batch that fails is read again record by record, so the error names the first bad record
    and its byte offset (``skip``: every bad record is dropped and counted instead).
    """
    size = _batch_size(fam)
    index = 0

    def flush(recs: list[bytes], offsets: list[int]) -> list[Any]:
        nonlocal index
        first = index
        index += len(recs)
        where = f"{rd.path} (records {first}..{index - 1}, from byte offset {offsets[0]})"
        try:
            return _decode(fam, recs, where, segments)
        except _MALFORMED:
            pass
        out: list[Any] = []
        for i, (rec, off) in enumerate(zip(recs, offsets, strict=True)):
            one = f"{rd.path}: record {first + i} at byte offset {off}"
            try:
                out.extend(_decode(fam, [rec], one, segments))
            except _MALFORMED as e:
                text = str(e) if isinstance(e, FormatError) else f"{type(e).__name__}: {e}"
                msg = (
                    f"{one}: not a valid {fam.name} record ({text.removeprefix(one + ': ')}); "
                    "the file is damaged: download it again, or pass --skip-corrupt to drop "
                    "bad records"
                )
                if not skip:
                    raise FormatError(msg) from None
                rd.stats.skipped += 1
                rd.stats.errors.append(msg)
        return out

    pending: list[bytes] = []
    pending_at: list[int] = []
    held = 0  # bytes in pending
    for batch, offsets in rd.batches_with_offsets():
        # a reader batch is one inflated chunk's worth of records: held overshoots by one at most
        pending.extend(batch)
        pending_at.extend(offsets)
        held += sum(map(len, batch))
        batch.clear()  # the reader's list too: a record lives on in pending only
        while len(pending) >= size or (pending and held >= _BATCH_BYTES):
            n = size if len(pending) >= size else len(pending)
            recs, at = pending[:n], pending_at[:n]
            pending, pending_at = pending[n:], pending_at[n:]
            held -= sum(map(len, recs))
            out = flush(recs, at)
            del recs  # decoded: the raw records go before the consumer gets the batch
            yield from out
    if pending:
        yield from flush(pending, pending_at)


def iter_raw(
    path: str | os.PathLike,
    family: str,
    *,
    verify: bool = True,
    on_error: str = "raise",
    reader: RecordReader | None = None,
) -> Iterator[Raw]:
    """Loader-shaped batches (dicts of arrays stacked on a record axis) of one shard, in order."""
    fam = get_family(family)
    rd = reader or reader_for(path, family, verify=verify, on_error=on_error)
    yield from _read(fam, rd, segments=False, skip=on_error == "skip")  # type: ignore[misc]


def iter_segments(
    path: str | os.PathLike,
    family: str,
    *,
    verify: bool = True,
    on_error: str = "raise",
    reader: RecordReader | None = None,
) -> Iterator[SegmentBatch]:
    """The shard's records as segment batches (each family's alignment rule), in order."""
    fam = get_family(family)
    rd = reader or reader_for(path, family, verify=verify, on_error=on_error)
    yield from _read(fam, rd, segments=True, skip=on_error == "skip")  # type: ignore[misc]


def read_raw(path: str | os.PathLike, family: str, **kw: Any) -> Raw:
    """A whole shard's loader-shaped arrays, concatenated on the record axis (small files)."""
    batches = list(iter_raw(path, family, **kw))
    if not batches:
        return {}
    keys = batches[0].keys()
    return {k: np.concatenate([b[k] for b in batches]) for k in keys}


def write_shard(
    path: str | os.PathLike, family: str, records: list[Mapping[str, np.ndarray]]
) -> None:
    """Write records (loader-shaped dicts, one per record) in the family's exact schema."""
    fam = get_family(family)
    with RecordWriter(path, compression=fam.compression) as w:
        for rec in records:
            w.write(fam.encode(rec))
