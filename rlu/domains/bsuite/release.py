"""bsuite's release family: transitions of 2 steps, as the release's notebook loads them.

discount_0 = discount[0] * (step_type[1] != LAST), so every LAST is terminal (the notebook's
loader).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from rlu.codecs import example as ex
from rlu.domains.records import (
    FIRST,
    LAST,
    Family,
    Raw,
    feature,
    integers,
    need,
    numeric,
    ragged,
    record_steps,
    split_rows,
    time_major,
)
from rlu.segments import SegmentBatch

_MiB, _GiB = 1 << 20, 1 << 30


def parse_bsuite(cols: Mapping[str, Any], where: str = "record") -> list[Raw]:
    n = len(next(iter(cols.values()))) if cols else 0
    if n == 0:
        return []
    if ragged(cols):
        return [b for row in split_rows(cols, n) for b in parse_bsuite(row, where)]
    t = numeric(need(cols, "reward", where), "reward", where).shape[1]
    out: Raw = {}
    for k, c in cols.items():
        c = numeric(c, k, where)
        if k in ("action", "step_type"):
            integers(c, k, where)
        out[k] = time_major(c, t, k, where, scalar=k != "observation")
    return [out]


def bsuite_segments(raw: Raw) -> SegmentBatch:
    n, t = record_steps(raw, "step_type")
    st = raw["step_type"]
    for k in ("discount", "reward", "action"):
        feature(raw, k, (n, t), 2)
    feature(raw, "observation", (n, t), 3)
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


FAMILIES = (
    Family(
        name="bsuite",
        compression="gzip",
        parse=parse_bsuite,
        segments=bsuite_segments,
        encode=encode_bsuite,
        whole_episodes=False,
        max_record_bytes=4 * _MiB,
        max_shard_bytes=1 * _GiB,
        record_note="a bsuite transition is a few kB",
    ),
)
