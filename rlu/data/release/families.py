"""The registry of the release's families, gathered from the domains, and shard reading through it.

Each domain's release module (``Domain.release_module``: ``rlu/domains/<name>/release.py``) lists
its families (:class:`rlu.domains.records.Family`), each with two views of its records
(docs/release_format.md §3, §4):

- ``parse``: the arrays the original loaders return (``dm_control_suite.py``'s parsed sequences,
  ``atari.py``'s tuple, ...): time-first float32 arrays, PNGs decoded, ids bitcast. ``encode`` is
  its inverse: it writes a record in the exact release schema (our writer for round trips).
- ``segments``: the same data in rlu's model (:class:`rlu.segments.Segment`, RLDS steps), by the
  family's alignment rule, which its module's docstring states and one test each in
  ``tests/release/test_families.py`` pins.

Where a segment's last step carries values the file holds (windows), they are kept, so that the
transition view yields exactly the loader's ``(o_t, a_t, r_t, d_t, o_tp1, a_tp1)``. Here: the
registry (:data:`FAMILIES`), a family's reader with its record limit, and a shard read in
batches, every bad record named.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from rlu.codecs import example as ex
from rlu.data.release.framing import RecordReader, RecordWriter
from rlu.domains import DOMAINS
from rlu.domains.records import Family, Raw
from rlu.segments import SegmentBatch
from rlu.types import FormatError


def _load() -> Mapping[str, Family]:
    out: dict[str, Family] = {}
    for domain in DOMAINS.values():
        for fam in domain.release_families():
            if not isinstance(fam, Family) or fam.name in out:
                raise FormatError(
                    f"{domain.release_module}.FAMILIES: {fam!r} is not a Family or names a "
                    "family twice; give each of the domain's families one Family entry"
                )
            out[fam.name] = fam
    return out


FAMILIES: Mapping[str, Family] = _load()
"""Every release family by name (the bucket's top folder), from each domain's release module."""


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
    size = fam.batch_records
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
