"""Atari's release families: ``atari.py``'s transitions and the ordered episodes TFDS reads.

- transitions (``atari``): 2 steps (o_t, o_tp1 stacks); reward_0 = r_t, discount_0 = d_t; d_t ==
  0 marks step 1 is_last + is_terminal; step 1's reward 0. r_t is the clipped reward (the only
  one these files hold); the file's clipped episode return goes to clipped_episode_return.
- ``atari_episodes_ordered``: rewards unshifted, the raw game score (unclipped_rewards; the file's
  clipped_rewards must equal clip(raw, -1, 1), checked); if the last discount is 0 the episode is
  terminal and discounts shift left with a 0 appended (TFDS ``atari_utils``); frames stored once,
  stacked 4 at sample time.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from rlu.codecs import example as ex
from rlu.codecs.png import encode_png
from rlu.domains.atari import ATARI_MAX_AGENT_STEPS
from rlu.domains.records import (
    Family,
    Raw,
    integers,
    need,
    numeric,
    png_stack,
    scalar,
    split_rows,
)
from rlu.segments import SegmentBatch
from rlu.types import FormatError

ATARI_FRAME = (84, 84)
_MiB, _GiB = 1 << 20, 1 << 30


def parse_atari_transitions(cols: Mapping[str, Any], where: str = "record") -> list[Raw]:
    """``atari.py``: four PNGs per observation stacked as channels; ids bitcast to uint64."""
    out: Raw = {}
    for k in ("o_t", "o_tp1"):
        col = need(cols, k, where)
        if not isinstance(col, ex.BytesColumn):
            raise FormatError(f"{where}: {k!r} must be a bytes_list of 4 PNG frames")
        frames = png_stack(col, 4, k, where, channels=1, size=ATARI_FRAME)
        arr = np.asarray(frames, np.uint8)
        if arr.ndim != 4 or arr.shape[2:] != ATARI_FRAME:
            raise FormatError(f"{where}: {k!r} frames must be 84x84 grey, got {arr.shape[2:]}")
        out[k] = np.ascontiguousarray(arr.transpose(0, 2, 3, 1))
    out["a_t"] = scalar(cols, "a_t", where, np.int32, integer=True)
    out["a_tp1"] = scalar(cols, "a_tp1", where, np.int32, integer=True)
    out["r_t"] = scalar(cols, "r_t", where, np.float32)
    out["d_t"] = scalar(cols, "d_t", where, np.float32)
    out["episode_id"] = scalar(cols, "episode_id", where, integer=True).view(np.uint64)
    out["episode_return"] = scalar(cols, "episode_return", where, np.float32)
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
    for row in split_rows(cols, n) if n > 1 else [cols]:
        col = need(row, "observations", where)
        if not isinstance(col, ex.BytesColumn):
            raise FormatError(f"{where}: 'observations' must be a bytes_list of PNG frames")
        t = integers(numeric(need(row, "actions", where), "actions", where), "actions", where)
        t = t.shape[1]
        if t > ATARI_MAX_AGENT_STEPS + 1:
            # checked before a frame is decoded: 100 MB of tiny PNGs would inflate to gigabytes
            raise FormatError(
                f"{where}: an episode of {t:,} steps; the recording stopped episodes at "
                f"{ATARI_MAX_AGENT_STEPS:,} agent steps (108,000 frames)"
            )
        rec: Raw = {}
        for k in _ATARI_EP_LISTS:
            v = numeric(need(row, k, where), k, where)
            if v.shape[1] != t:
                raise FormatError(f"{where}: {k!r} has {v.shape[1]} steps, 'actions' has {t}")
            rec[k] = v[0]
        frames = png_stack(col, t, "observations", where, channels=1, size=ATARI_FRAME)[0]
        rec["observations"] = np.asarray(frames, np.uint8).reshape(t, *ATARI_FRAME)
        for k in _ATARI_EP_SCALARS:
            rec[k] = scalar(row, k, where, integer=k.endswith("_idx"))[0]
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


# Limits: well above what the release holds (sizes from the TFDS catalog, which describe the same
# data re-encoded; docs/release_format.md §5), well below what a machine cannot hold.
# A transition is 8 PNG frames (tens of kB), an episode up to 27,000 (tens of MB); a run is
# about 75 GiB in 100 shards (or 50 episode shards). An episode of frames decodes to ~28x its PNG
# bytes (a Pong frame: 250 B -> 7 kB), so 64 of them held ~750 MB (bench/cluster.py); 4 bound a
# conversion job at ~1/16 of that and decode as fast (a record is hundreds to thousands of frames).
# Job memory: an episode shard job of real frames (Pong, MsPacman) peaked at 174-186 MB
# (bench/README.md); 4 episodes of 27,000 frames, the longest the release has, decode to 760 MB.
FAMILIES = (
    Family(
        name="atari",
        compression="gzip",
        parse=parse_atari_transitions,
        segments=atari_transition_segments,
        encode=encode_atari_transition,
        whole_episodes=False,
        max_record_bytes=4 * _MiB,
        max_shard_bytes=4 * _GiB,
        record_note="an Atari transition is 8 PNG frames, tens of kB",
        batch_records=64,
        image_encoding="zlib",
        whole_stacks=True,
        reward_note=(
            "clipped to [-1, 1]: r_t of the release's transition files is the reward the "
            "recording DQN stored (Dopamine's runner clips before storing; atari.py documents "
            "the episode return as clipped). The raw game score is not in these files: "
            "episode_return is missing and clipped_episode_return holds the file's clipped "
            "return."
        ),
    ),
    Family(
        name="atari_episodes_ordered",
        compression="gzip",
        parse=parse_atari_episodes,
        segments=atari_episode_segment,
        encode=encode_atari_episode,
        whole_episodes=True,
        max_record_bytes=128 * _MiB,
        max_shard_bytes=8 * _GiB,
        record_note="an Atari episode is at most 27,000 PNG frames, tens of MB",
        batch_records=4,
        job_memory=1 << 30,
        image_encoding="zlib",
        reward_note=(
            "raw game score (the file's unclipped_rewards); the clipped reward is clip(r, -1, 1), "
            "checked against the file's clipped_rewards. episode_return is the raw sum, "
            "clipped_episode_return the clipped one."
        ),
    ),
)
