"""RWRL's release family: ``rwrl.py``'s whole episodes of 1001 flat float steps.

Index 0 of action / reward / discount is a placeholder: action_t = action[t+1] (last repeated),
reward_t = reward[t+1], discount_t = discount[t+1] (``rwrl.py``); keys nest with ':'.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from rlu.codecs import example as ex
from rlu.domains.records import (
    Family,
    Raw,
    feature,
    need,
    numeric,
    ragged,
    split_rows,
    time_major,
)
from rlu.segments import SegmentBatch
from rlu.types import FormatError

_MiB, _GiB = 1 << 20, 1 << 30


def parse_rwrl(cols: Mapping[str, Any], where: str = "record") -> list[Raw]:
    """``rwrl.py``: flat float lists of T (1001) steps; keys nest with ':'."""
    n = len(next(iter(cols.values()))) if cols else 0
    if n == 0:
        return []
    if ragged(cols):
        return [b for row in split_rows(cols, n) for b in parse_rwrl(row, where)]
    t = numeric(need(cols, "reward", where), "reward", where).shape[1]
    out: Raw = {}
    for k, c in cols.items():
        c = numeric(c, k, where)
        out[k] = time_major(c, t, k, where, scalar=False)
    return [out]


def rwrl_segments(raw: Raw) -> SegmentBatch:
    obs = {
        k[len("observation:") :].replace(":", "/"): v
        for k, v in raw.items()
        if k.startswith("observation:")
    }
    if not obs:
        raise FormatError(f"RWRL record has no observation:* features; found {sorted(raw)}")
    n, t = feature(raw, "reward", (), 3).shape[:2]
    if n < 1 or t < 1:
        raise FormatError(f"feature 'reward' has shape {raw['reward'].shape}: no steps")
    for k in ("reward", "discount"):
        if feature(raw, k, (n, t), 3).shape[2] != 1:
            raise FormatError(f"feature {k!r} holds {raw[k].shape[2]} values per step; want 1")
    obs = {k: feature({k: v}, k, (n, t)) for k, v in obs.items()}
    action = feature(raw, "action", (n, t), 3)
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


# Limits: well above what the release holds (sizes from the TFDS catalog, which describe the same
# data re-encoded; docs/release_format.md §5), well below what a machine cannot hold.
# An episode of 1000 steps is under 1 MB; the release is 6.78 GiB in 391 shards.
FAMILIES = (
    Family(
        name="rwrl",
        compression=None,
        parse=parse_rwrl,
        segments=rwrl_segments,
        encode=encode_rwrl,
        whole_episodes=True,
        max_record_bytes=32 * _MiB,
        max_shard_bytes=1 * _GiB,
        record_note="an RWRL episode of 1000 steps is under 1 MB",
    ),
)
