"""What every domain's release family is built of: the Family entry and the record helpers.

A domain's release module (``rlu/domains/<name>/release.py``, named by ``Domain.release_module``)
lists its :class:`Family` entries in ``FAMILIES``: how one of its records, decoded by
``rlu.codecs.example`` into columns, becomes the arrays the original loaders return (``parse``),
how those become rlu's segments (``segments``, :class:`rlu.segments.SegmentBatch`) and how a
record is written back in the release's exact schema (``encode``). ``rlu.data.release.families``
gathers every domain's entries into the one registry the reader, downloader and converter use.

The helpers below check each feature a parser takes (every malformed record is a
:class:`~rlu.types.FormatError` naming it). The control suite's and locomotion's files share one
record layout, ``dm_control_suite.py``'s sequences; its parse, segments and encode are here too.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from rlu.codecs import example as ex
from rlu.codecs.png import decode_png
from rlu.segments import SegmentBatch
from rlu.types import FormatError

FIRST, MID, LAST = 0, 1, 2
"""dm_env's step types, as the release stores them."""
Raw = dict[str, np.ndarray]
"""A batch of records as the original loaders return them: arrays stacked on a record axis."""
CAMERA_KEY = "observation/walker/egocentric_camera"
CAMERA_SHAPE = (64, 64, 3)
WINDOW_SCALARS = ("reward", "discount", "step_type", "episodic_reward")


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
    batch_records: int = 4096
    """Records decoded together (a batch is also cut at 64 MB of records): fewer where a record
    decodes to much more than its bytes (PNG frames)."""
    job_memory: int = 512 << 20
    """Memory one shard's conversion job asks Ray for (bytes), so that a node runs no more of
    them at once than its memory holds."""
    image_encoding: str = "raw"
    """How a converted dataset stores its images by default (``zlib`` for Atari's frames)."""
    whole_stacks: bool = False
    """Each record's observations are whole frame stacks (Atari's transition files): the
    converted dataset keeps the stacks instead of storing each frame once."""
    reward_note: str | None = None
    """What the family's stored reward is, written into a converted dataset's manifest (Atari's
    clipped or raw score); None: the reward is the environment's."""


# --- the checks of a record's features --------------------------------------------------------


def need(cols: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in cols:
        raise FormatError(f"{where}: feature {key!r} is missing; found {sorted(cols)}")
    return cols[key]


def feature(raw: Raw, key: str, lead: tuple[int, ...], ndim: int | None = None) -> np.ndarray:
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


def record_steps(raw: Raw, key: str) -> tuple[int, int]:
    """(records, steps) of the time-major scalar feature ``key``, at least one of each."""
    v = feature(raw, key, (), 2)
    if v.shape[0] < 1 or v.shape[1] < 1:
        raise FormatError(f"feature {key!r} has shape {v.shape}: no steps")
    return v.shape


def numeric(col: Any, key: str, where: str) -> np.ndarray:
    if isinstance(col, ex.BytesColumn):
        raise FormatError(f"{where}: feature {key!r} is a bytes_list; a numeric list was expected")
    if col.dtype == object:
        raise FormatError(f"{where}: feature {key!r} has different lengths across records")
    return col


def scalar(
    cols: Mapping[str, Any],
    key: str,
    where: str,
    dtype: type[np.generic] | None = None,
    integer: bool = False,
) -> np.ndarray:
    v = numeric(need(cols, key, where), key, where)
    if integer:
        integers(v, key, where)
    if v.ndim != 2 or v.shape[1] != 1:
        raise FormatError(f"{where}: feature {key!r} must hold one value, it holds {v.shape[1:]}")
    v = v[:, 0]
    return v.astype(dtype) if dtype is not None else v


def integers(v: np.ndarray, key: str, where: str) -> np.ndarray:
    """``v``, which the release stores as an int64_list (actions, ids, indices)."""
    if v.dtype != np.int64:
        raise FormatError(
            f"{where}: feature {key!r} is a float_list; the release stores it as an int64_list"
        )
    return v


def time_major(v: np.ndarray, t: int, key: str, where: str, scalar: bool) -> np.ndarray:
    n, count = v.shape
    if t == 0 or count % t:
        raise FormatError(f"{where}: feature {key!r} holds {count} values, not a multiple of T={t}")
    return v.reshape(n, t) if scalar and count == t else v.reshape(n, t, count // t)


def split_rows(cols: Mapping[str, Any], n: int) -> list[dict[str, Any]]:
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


def ragged(cols: Mapping[str, Any]) -> bool:
    return any(not isinstance(c, ex.BytesColumn) and c.dtype == object for c in cols.values())


def png_stack(
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


# --- dm_control sequences: the control suite's and locomotion's windows and episodes ----


def parse_sequences(cols: Mapping[str, Any], where: str = "record") -> list[Raw]:
    """``dm_control_suite.py``'s parse: every list reshaped (T, ...) time first; camera raw uint8.

    Returns one stacked dict per run of records of equal T (usually one for a whole batch).
    """
    if not cols:
        return []
    n = len(next(iter(cols.values())))
    if ragged(cols):
        return [b for row in split_rows(cols, n) for b in parse_sequences(row, where)]
    t = numeric(need(cols, "discount", where), "discount", where).shape[1]
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
            out[k] = time_major(c, t, k, where, scalar=k in WINDOW_SCALARS)
    out["length"] = np.full(n, t, np.int32)
    return [out]


def observation_of(raw: Raw, prefix: str = "observation/") -> dict[str, np.ndarray]:
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
    n, t = record_steps(raw, "discount")
    step_type = feature(raw, "step_type", (n, t), 2)
    discount = raw["discount"].astype(np.float32)
    feature(raw, "reward", (n, t), 2)
    feature(raw, "action", (n, t), 3)
    obs = {k: feature(raw, f"observation/{k}", (n, t)) for k in observation_of(raw)}
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
    n, t = record_steps(raw, "reward")
    reward = raw["reward"].astype(np.float32)
    discount = feature(raw, "discount", (n, t), 2).astype(np.float32)
    feature(raw, "action", (n, t), 3)
    obs = {k: feature(raw, f"observation/{k}", (n, t)) for k in observation_of(raw)}
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
        ids = feature(raw, "episode_id", (n,), 1)
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
