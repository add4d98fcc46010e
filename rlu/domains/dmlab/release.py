"""DMLab's release family: fixed-length episodes of 72x96x3 PNG frames.

Values as stored; pixels are kept in the stored BGR order by ``parse`` (as the notebook) and turned
to RGB in the segments.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from rlu.codecs import example as ex
from rlu.codecs.png import encode_png
from rlu.domains.records import (
    Family,
    Raw,
    feature,
    integers,
    need,
    numeric,
    png_stack,
    record_steps,
    scalar,
    split_rows,
)
from rlu.segments import SegmentBatch
from rlu.types import FormatError

DMLAB_FRAME = (72, 96, 3)
_MiB, _GiB = 1 << 20, 1 << 30

_DMLAB_LISTS = ("actions", "rewards", "discounts", "discounted_rewards", "observations_reward")


def parse_dmlab(cols: Mapping[str, Any], where: str = "record") -> list[Raw]:
    """DMLab episodes: T PNG frames 72x96x3 returned in the stored BGR order (as the notebook)."""
    n = len(next(iter(cols.values()))) if cols else 0
    out = []
    for row in split_rows(cols, n) if n > 1 else [cols]:
        t = integers(numeric(need(row, "actions", where), "actions", where), "actions", where)
        t = t.shape[1]
        if t < 1:
            raise FormatError(f"{where}: 'actions' is empty; an episode has at least one step")
        rec: Raw = {}
        for k in _DMLAB_LISTS:
            if k in row:
                v = numeric(row[k], k, where)[0]
                if v.size != t:
                    raise FormatError(f"{where}: {k!r} holds {v.size} values, 'actions' {t}")
                rec[k] = v.reshape(t)
        last_action = numeric(
            need(row, "observations_action", where), "observations_action", where
        )[0]
        if last_action.size == 0 or last_action.size % t:
            raise FormatError(
                f"{where}: 'observations_action' holds {last_action.size} values, not a "
                f"multiple of the {t} steps"
            )
        rec["observations_action"] = last_action.reshape(t, -1)
        col = need(row, "observations_pixels", where)
        if not isinstance(col, ex.BytesColumn):
            raise FormatError(f"{where}: 'observations_pixels' must be a bytes_list of PNGs")
        frames = png_stack(col, t, "observations_pixels", where, 3, DMLAB_FRAME[:2])[0]
        rec["observations_pixels"] = np.asarray(frames, np.uint8).reshape(t, *DMLAB_FRAME)
        for k in ("episode_id", "start_idx", "episode_return"):
            if k in row:
                rec[k] = scalar(row, k, where, integer=k != "episode_return")[0]
        out.append({k: np.asarray(v)[None] for k, v in rec.items()})
    return out


def dmlab_segment(raw: Raw) -> SegmentBatch:
    n, t = record_steps(raw, "actions")
    for k in ("discounts", "rewards", "observations_reward"):
        feature(raw, k, (n, t), 2)
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


# Limits: well above what the release holds (sizes from the TFDS catalog, which describe the same
# data re-encoded; docs/release_format.md §5), well below what a machine cannot hold.
# An episode of 72x96 PNG frames is 3-14 MB on average; shards are 145-265 MB. An episode
# decodes to many times its PNG bytes: 4 a batch bound a conversion job's memory.
FAMILIES = (
    Family(
        name="dmlab",
        compression="gzip",
        parse=parse_dmlab,
        segments=dmlab_segment,
        encode=encode_dmlab,
        whole_episodes=True,
        max_record_bytes=128 * _MiB,
        max_shard_bytes=4 * _GiB,
        record_note="a DMLab episode of 72x96 PNG frames is 3-14 MB on average",
        batch_records=4,
        job_memory=1 << 30,
    ),
)
