"""``tf.train.Example`` to numpy and back, without protobuf or TensorFlow.

Wire layout (tensorflow/core/example/{example,feature}.proto; docs/release_format.md §1.3)::

    Example  { 1: Features }
    Features { 1: repeated MapEntry { 1: string key, 2: Feature } }
    Feature  { oneof: 1: BytesList, 2: FloatList, 3: Int64List }
    *List    { 1: repeated value }   # floats packed fixed32, int64 packed varints, bytes entries

Decoded values: float lists -> float32 arrays, int64 lists -> int64 arrays, bytes lists -> lists of
bytes. Packed and unpacked numeric encodings are both accepted, unknown fields are skipped, and a
repeated map key keeps its last value (protobuf semantics). Any malformed input raises
:class:`~rlu.types.FormatError` and nothing else.

Why a hand-written decoder rather than the protobuf runtime: see :mod:`bench.release_reader`
(``--decoders``). The runtime parses fast, but turning a ``RepeatedScalarContainer`` into numpy
builds one Python float per value; here packed floats become arrays by ``np.frombuffer`` on the
payload, and whole batches of same-shaped records (every window file of the release) are decoded
as columns of one 2D byte array (:func:`decode_batch`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rlu.types import FormatError

Feature = np.ndarray | list
"""float32 array, int64 array, or list of bytes."""

BYTES, FLOAT, INT64 = 1, 2, 3
_KIND_NAMES = {BYTES: "bytes_list", FLOAT: "float_list", INT64: "int64_list"}
_EMPTY_F32 = np.zeros(0, np.float32)
_SHIFTS = np.arange(0, 70, 7, dtype=np.uint64)


class ExampleError(FormatError):
    """Bytes that are not a valid serialized ``tf.train.Example``."""


def _err(what: str, pos: int) -> ExampleError:
    return ExampleError(f"not a valid tf.train.Example: {what} at payload byte {pos}")


# --- scalar decoding -----------------------------------------------------------------------


def _varint(buf: bytes, pos: int, end: int) -> tuple[int, int]:
    if pos >= end:
        raise _err("truncated varint", pos)
    b = buf[pos]
    if b < 0x80:
        return b, pos + 1
    result = b & 0x7F
    shift = 7
    p = pos + 1
    while True:
        if p >= end:
            raise _err("truncated varint", pos)
        b = buf[p]
        p += 1
        result |= (b & 0x7F) << shift
        if b < 0x80:
            return result & 0xFFFFFFFFFFFFFFFF, p
        shift += 7
        if shift >= 70:
            raise _err("varint longer than 10 bytes", pos)


def _tag(buf: bytes, pos: int, end: int) -> tuple[int, int]:
    """A field's tag; field number 0 is invalid protobuf (and a flood of zero bytes is no
    message)."""
    tag, p = _varint(buf, pos, end)
    if tag < 8:
        raise _err(f"invalid tag {tag} (field number 0)", pos)
    return tag, p


def _skip(buf: bytes, pos: int, end: int, wire: int) -> int:
    if wire == 0:
        return _varint(buf, pos, end)[1]
    if wire == 1:
        p = pos + 8
    elif wire == 2:
        n, p = _varint(buf, pos, end)
        p += n
    elif wire == 5:
        p = pos + 4
    else:  # groups (3, 4) are not used by Example; 6 and 7 are invalid
        raise _err(f"unsupported wire type {wire}", pos)
    if p > end:
        raise _err("field runs past the end of its message", pos)
    return p


def _len_delim(buf: bytes, pos: int, end: int) -> tuple[int, int]:
    n, p = _varint(buf, pos, end)
    if p + n > end:
        raise _err(f"length {n} runs past the end of its message", pos)
    return p, p + n


def decode_varints(data: bytes | np.ndarray) -> np.ndarray:
    """Packed varints -> int64 (two's complement, as protobuf's int64)."""
    b = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data
    if b.size == 0:
        return np.zeros(0, np.int64)
    last = b < 0x80
    if not last[-1]:
        raise _err("truncated packed varint list", int(b.size))
    ends = np.flatnonzero(last)
    starts = np.empty_like(ends)
    starts[0] = 0
    starts[1:] = ends[:-1] + 1
    lens = ends - starts + 1
    if lens.max() > 10:
        raise _err("varint longer than 10 bytes", int(starts[np.argmax(lens > 10)]))
    if lens.max() == 1:
        return b.astype(np.int64)
    pos_in = np.arange(b.size) - np.repeat(starts, lens)
    parts = (b & 0x7F).astype(np.uint64) << _SHIFTS[pos_in]
    return np.add.reduceat(parts, starts).view(np.int64)


def _parse_list(buf: bytes, pos: int, end: int, kind: int) -> Feature:
    if kind == BYTES:
        out: list[bytes] = []
        while pos < end:
            tag, pos = _tag(buf, pos, end)
            if tag == 0x0A:
                a, pos = _len_delim(buf, pos, end)
                out.append(buf[a:pos])
            else:
                pos = _skip(buf, pos, end, tag & 7)
        return out
    pieces: list[np.ndarray] = []
    while pos < end:
        tag, pos = _tag(buf, pos, end)
        if tag == 0x0A:  # packed
            a, pos = _len_delim(buf, pos, end)
            if kind == FLOAT:
                if (pos - a) % 4:
                    raise _err("packed float list whose length is not a multiple of 4", a)
                pieces.append(np.frombuffer(buf, "<f4", (pos - a) // 4, a))
            else:
                pieces.append(decode_varints(buf[a:pos]))
        elif tag == 0x0D and kind == FLOAT:  # one unpacked fixed32
            if pos + 4 > end:
                raise _err("truncated float", pos)
            pieces.append(np.frombuffer(buf, "<f4", 1, pos))
            pos += 4
        elif tag == 0x08 and kind == INT64:  # one unpacked varint
            v, pos = _varint(buf, pos, end)
            pieces.append(np.array([v], np.uint64).view(np.int64))
        else:
            pos = _skip(buf, pos, end, tag & 7)
    dtype = np.float32 if kind == FLOAT else np.int64
    if not pieces:
        return np.zeros(0, dtype)
    arr = pieces[0] if len(pieces) == 1 else np.concatenate(pieces)
    return arr.astype(dtype, copy=False)


def _parse_feature(buf: bytes, pos: int, end: int) -> Feature:
    value: Feature = _EMPTY_F32
    kind = 0
    while pos < end:
        tag, pos = _tag(buf, pos, end)
        field, wire = tag >> 3, tag & 7
        if wire == 2 and field in _KIND_NAMES:
            a, pos = _len_delim(buf, pos, end)
            v = _parse_list(buf, a, pos, field)
            if field == kind:  # a repeated sub-message merges (lists concatenate)
                v = value + v if field == BYTES else np.concatenate([value, v])
            value, kind = v, field
        else:
            pos = _skip(buf, pos, end, wire)
    return value


def _map_entry(buf: bytes, pos: int, end: int, parse_value: Any, value: Any) -> tuple[str, Any]:
    """One ``map<string, Feature>`` entry: its key and ``parse_value`` of its Feature bytes
    (``value`` when the entry has none)."""
    key = b""
    while pos < end:
        tag, pos = _tag(buf, pos, end)
        if tag == 0x0A:
            a, pos = _len_delim(buf, pos, end)
            key = buf[a:pos]
        elif tag == 0x12:
            a, pos = _len_delim(buf, pos, end)
            value = parse_value(buf, a, pos)
        else:
            pos = _skip(buf, pos, end, tag & 7)
    try:
        return key.decode("utf-8"), value
    except UnicodeDecodeError:
        raise _err(f"feature key {key!r} is not UTF-8", pos) from None


def _parse_entry(buf: bytes, pos: int, end: int) -> tuple[str, Feature]:
    return _map_entry(buf, pos, end, _parse_feature, _EMPTY_F32)


def decode_example(payload: bytes) -> dict[str, Feature]:
    """One serialized ``tf.train.Example`` -> {key: float32 array | int64 array | [bytes]}."""
    if not isinstance(payload, bytes):
        payload = bytes(payload)
    out: dict[str, Feature] = {}
    pos, end = 0, len(payload)
    while pos < end:
        tag, pos = _tag(payload, pos, end)
        if tag == 0x0A:  # Example.features
            a, pos = _len_delim(payload, pos, end)
            q = a
            while q < pos:
                t, q = _tag(payload, q, pos)
                if t == 0x0A:  # Features.feature map entry
                    b, q = _len_delim(payload, q, pos)
                    k, v = _parse_entry(payload, b, q)
                    out[k] = v
                else:
                    q = _skip(payload, q, pos, t & 7)
        else:
            pos = _skip(payload, pos, end, tag & 7)
    return out


# --- batch decoding of same-shaped records -------------------------------------------------


@dataclass
class _Span:
    start: int
    end: int
    kind: int  # FLOAT: fixed32 bytes, INT64: varint bytes, BYTES: one bytes entry


def _layout(payload: bytes) -> dict[str, list[_Span]]:
    """Where each feature's value bytes lie in ``payload`` (every other byte is structure)."""
    spans: dict[str, list[_Span]] = {}
    pos, end = 0, len(payload)
    while pos < end:
        tag, pos = _tag(payload, pos, end)
        if tag != 0x0A:
            pos = _skip(payload, pos, end, tag & 7)
            continue
        a, pos = _len_delim(payload, pos, end)
        q = a
        while q < pos:
            t, q = _tag(payload, q, pos)
            if t != 0x0A:
                q = _skip(payload, q, pos, t & 7)
                continue
            b, q = _len_delim(payload, q, pos)
            key, fspans = _layout_entry(payload, b, q)
            spans[key] = fspans  # a repeated key: the earlier value's bytes count as structure
    return spans


def _layout_entry(buf: bytes, pos: int, end: int) -> tuple[str, list[_Span]]:
    return _map_entry(buf, pos, end, _layout_feature, [])


def _layout_feature(buf: bytes, pos: int, end: int) -> list[_Span]:
    spans: list[_Span] = []
    kind = 0
    while pos < end:
        tag, pos = _tag(buf, pos, end)
        field, wire = tag >> 3, tag & 7
        if not (wire == 2 and field in _KIND_NAMES):
            pos = _skip(buf, pos, end, wire)
            continue
        a, lend = _len_delim(buf, pos, end)
        pos = lend
        if field != kind:
            spans = []
            kind = field
        q = a
        while q < lend:
            t, q = _tag(buf, q, lend)
            if t == 0x0A:
                s, q = _len_delim(buf, q, lend)
                if field == FLOAT and (q - s) % 4:
                    raise _err("packed float list whose length is not a multiple of 4", s)
                if field == INT64 and q > s:
                    decode_varints(buf[s:q])  # validates
                spans.append(_Span(s, q, field))
            elif t == 0x0D and field == FLOAT:
                if q + 4 > lend:
                    raise _err("truncated float", q)
                spans.append(_Span(q, q + 4, FLOAT))
                q += 4
            elif t == 0x08 and field == INT64:
                s = q
                _, q = _varint(buf, q, lend)
                spans.append(_Span(s, q, INT64))
            else:
                q = _skip(buf, q, lend, t & 7)
    if not spans and kind:
        spans = [_Span(pos, pos, kind)]  # an empty list of this kind
    return spans


class BytesColumn:
    """A bytes feature over a batch: ``values[i]`` is record i's list of entries.

    When every record's entries have the same lengths (raw camera bytes), ``flat`` holds the
    concatenated entries as one (N, total) uint8 array, built without Python per record.
    """

    def __init__(
        self,
        values: list[list[bytes]] | None = None,
        flat: np.ndarray | None = None,
        entry_lengths: Sequence[int] | None = None,
    ):
        self._values = values
        self.flat = flat
        self.entry_lengths = tuple(entry_lengths) if entry_lengths is not None else None

    def __len__(self) -> int:
        return len(self._values) if self._values is not None else int(self.flat.shape[0])  # type: ignore[union-attr]

    @property
    def values(self) -> list[list[bytes]]:
        if self._values is None:
            assert self.flat is not None and self.entry_lengths is not None
            cuts = np.cumsum((0, *self.entry_lengths))
            self._values = [
                [row[cuts[j] : cuts[j + 1]].tobytes() for j in range(len(self.entry_lengths))]
                for row in self.flat
            ]
        return self._values

    def concatenated(self) -> np.ndarray:
        """(N, total) uint8 of each record's entries joined; records must agree in total length."""
        if self.flat is not None:
            return self.flat
        joined = [b"".join(v) for v in self.values]
        sizes = {len(j) for j in joined}
        if len(sizes) > 1:
            raise FormatError(f"bytes entries differ in total length across records: {sizes}")
        total = sizes.pop() if sizes else 0
        return np.frombuffer(b"".join(joined), np.uint8).reshape(len(joined), total)


Column = np.ndarray | BytesColumn
"""Numeric: (N, count) array when counts agree, else an object array of 1D arrays."""


def _template_decode(
    payloads: Sequence[bytes], layout: dict[str, list[_Span]]
) -> tuple[dict[str, Column], np.ndarray]:
    """Decode records that share ``layout``'s structure; returns (columns, ok mask)."""
    n, length = len(payloads), len(payloads[0])
    P = np.frombuffer(b"".join(payloads), np.uint8).reshape(n, length)
    structure = np.ones(length, bool)
    varint_cols: list[np.ndarray] = []
    for spans in layout.values():
        for s in spans:
            structure[s.start : s.end] = False
            if s.kind == INT64:
                varint_cols.append(np.arange(s.start, s.end))
    ref = P[0]
    ok = (P[:, structure] == ref[structure]).all(axis=1)
    if varint_cols:
        vc = np.concatenate(varint_cols)
        ok &= ((P[:, vc] & 0x80) == (ref[vc] & 0x80)).all(axis=1)
    Q = P[ok] if not ok.all() else P
    cols: dict[str, Column] = {}
    for key, spans in layout.items():
        kind = spans[0].kind if spans else FLOAT
        idx = (
            np.concatenate([np.arange(s.start, s.end) for s in spans])
            if spans
            else np.zeros(0, np.intp)
        )
        contiguous = len(spans) == 1
        block = Q[:, spans[0].start : spans[0].end] if contiguous else Q[:, idx]
        if kind == FLOAT:
            cols[key] = np.ascontiguousarray(block).view("<f4").astype(np.float32, copy=False)
        elif kind == INT64:
            if block.shape[1] == 0:
                cols[key] = np.zeros((Q.shape[0], 0), np.int64)
                continue
            r = ref[idx]
            last = r < 0x80
            ends = np.flatnonzero(last)
            starts = np.concatenate([[0], ends[:-1] + 1])
            pos_in = np.arange(r.size) - np.repeat(starts, ends - starts + 1)
            if (ends - starts).max() == 0:
                cols[key] = block.astype(np.int64)
            else:
                parts = (block & 0x7F).astype(np.uint64) << _SHIFTS[pos_in]
                cols[key] = np.add.reduceat(parts, starts, axis=1).view(np.int64)
        else:  # bytes entries, all non-empty (_layout_is_simple)
            cols[key] = BytesColumn(
                flat=np.ascontiguousarray(block), entry_lengths=[s.end - s.start for s in spans]
            )
    return cols, ok


def decode_batch(payloads: Sequence[bytes], template_min: int = 8) -> dict[str, Column]:
    """Decode many records into columns (record order kept).

    Records of equal length whose structural bytes (tags, keys, lengths, varint continuation
    bits) equal the first one's are decoded together as columns of one 2D byte array; any other
    record goes through :func:`decode_example`. Both paths give identical values.
    """
    n = len(payloads)
    if n == 0:
        return {}
    if n >= template_min and len(set(map(len, payloads))) == 1:
        first = bytes(payloads[0])
        layout = _layout(first)
        if _layout_is_simple(layout, first):
            cols, ok = _template_decode(payloads, layout)
            if ok.all():
                return cols
            # Rare: some records differ in structure. Decode those one by one and merge.
            rest = [decode_example(payloads[i]) for i in np.flatnonzero(~ok).tolist()]
            return _merge(cols, ok, rest)
    return stack_examples([decode_example(p) for p in payloads])


def _layout_is_simple(layout: dict[str, list[_Span]], payload: bytes) -> bool:
    # An empty bytes list and a list holding one empty entry share a layout; let the scalar path
    # handle such records (no release file has them).
    for spans in layout.values():
        if spans and spans[0].kind == BYTES and any(s.start == s.end for s in spans):
            return False
    return True


def _merge(cols: dict[str, Column], ok: np.ndarray, rest: list[dict[str, Feature]]) -> dict:
    n = ok.size
    good = np.flatnonzero(ok)
    bad = np.flatnonzero(~ok)
    per_record: list[dict[str, Feature] | None] = [None] * n
    for j, i in enumerate(bad):
        per_record[i] = rest[j]
    for j, i in enumerate(good):
        rec: dict[str, Feature] = {}
        for k, c in cols.items():
            rec[k] = c.values[j] if isinstance(c, BytesColumn) else c[j]
        per_record[i] = rec
    return stack_examples(per_record)  # type: ignore[arg-type]


def stack_examples(records: Sequence[Mapping[str, Feature]]) -> dict[str, Column]:
    """Per-record dicts -> columns; a key missing from a record reads as an empty list."""
    keys: dict[str, int] = {}
    for r in records:
        for k, v in r.items():
            keys.setdefault(k, BYTES if isinstance(v, list) else 0)
    cols: dict[str, Column] = {}
    for k, kind in keys.items():
        if kind == BYTES:
            cols[k] = BytesColumn(values=[list(r.get(k, [])) for r in records])
            continue
        got = [r.get(k, _EMPTY_F32) for r in records]
        vals = [v if isinstance(v, np.ndarray) else np.zeros(0, np.float32) for v in got]
        dtypes = {v.dtype for v in vals if v.size}
        dtype = dtypes.pop() if len(dtypes) == 1 else (np.float32 if not dtypes else None)
        if dtype is None:
            raise FormatError(f"feature {k!r} has different list types across records")
        sizes = {v.size for v in vals}
        if len(sizes) == 1:
            cols[k] = np.stack(vals).astype(dtype, copy=False) if vals else np.zeros((0, 0), dtype)
        else:
            arr = np.empty(len(vals), object)
            for i, v in enumerate(vals):
                arr[i] = v.astype(dtype, copy=False)
            cols[k] = arr
    return cols


# --- encoding ------------------------------------------------------------------------------


def _enc_varint(v: int) -> bytes:
    v &= 0xFFFFFFFFFFFFFFFF
    out = bytearray()
    while v >= 0x80:
        out.append((v & 0x7F) | 0x80)
        v >>= 7
    out.append(v)
    return bytes(out)


def encode_varints(values: np.ndarray) -> bytes:
    """int64 (or uint64) values -> packed varints (negatives take 10 bytes, as in protobuf)."""
    v = np.asarray(values).astype(np.int64, copy=False).view(np.uint64).ravel()
    if v.size == 0:
        return b""
    groups = (v[:, None] >> _SHIFTS[None, :]) & np.uint64(0x7F)
    nbytes = np.ones(v.size, np.int64)
    for k in range(1, 10):
        nbytes[(v >> np.uint64(7 * k)) != 0] = k + 1
    cont = np.arange(10)[None, :] < (nbytes[:, None] - 1)
    b = (groups | (cont.astype(np.uint64) << np.uint64(7))).astype(np.uint8)
    keep = np.arange(10)[None, :] < nbytes[:, None]
    return b[keep].tobytes()


def _ld(field: int, payload: bytes) -> bytes:
    return _enc_varint((field << 3) | 2) + _enc_varint(len(payload)) + payload


def _kind_of(value: Any) -> tuple[int, Any]:
    if isinstance(value, (bytes, bytearray, str)):
        value = [value]
    if isinstance(value, (list, tuple)) and (
        not value or isinstance(value[0], (bytes, bytearray, str))
    ):
        if value and isinstance(value[0], (bytes, bytearray, str)):
            return BYTES, [v.encode() if isinstance(v, str) else bytes(v) for v in value]
        return FLOAT, np.zeros(0, np.float32)
    arr = np.asarray(value)
    if arr.dtype.kind == "f":
        return FLOAT, arr.astype("<f4").ravel()
    if arr.dtype.kind in "iub":
        if arr.dtype == np.uint64:
            arr = arr.view(np.int64)
        return INT64, arr.astype(np.int64).ravel()
    raise TypeError(f"cannot encode a {arr.dtype} value as a tf.train.Feature")


def encode_feature(value: Any, packed: bool = True, kind: int | None = None) -> bytes:
    k, v = _kind_of(value)
    if kind is not None and kind != k:
        if kind == FLOAT:
            v = np.asarray(v, np.float32).ravel()
        elif kind == INT64:
            v = np.asarray(v).astype(np.int64).ravel()
        k = kind
    if k == BYTES:
        body = b"".join(_ld(1, e) for e in v)
    elif k == FLOAT:
        if packed:
            body = _ld(1, v.astype("<f4").tobytes()) if v.size else b""
        else:
            body = b"".join(b"\x0d" + x.tobytes() for x in v.astype("<f4"))
    else:
        if packed:
            body = _ld(1, encode_varints(v)) if v.size else b""
        else:
            body = b"".join(b"\x08" + _enc_varint(int(x)) for x in v)
    return _ld(k, body)


def encode_example(
    features: Mapping[str, Any], packed: bool = True, kinds: Mapping[str, int] | None = None
) -> bytes:
    """{key: array | bytes | [bytes]} -> serialized ``tf.train.Example`` (keys sorted, as TF).

    Float arrays become float_list, integer / bool arrays int64_list (uint64 reinterpreted),
    bytes and lists of bytes bytes_list; ``kinds`` forces a list type per key (e.g. step_type
    stored as float).
    """
    kinds = kinds or {}
    entries = []
    for key in sorted(features):
        feat = encode_feature(features[key], packed=packed, kind=kinds.get(key))
        entries.append(_ld(1, _ld(1, key.encode("utf-8")) + _ld(2, feat)))
    return _ld(1, b"".join(entries))
