"""TFRecord framing without TensorFlow: reader and writer, whole-file gzip, CRC-32C checks.

A TFRecord file is a concatenation of records, each ``uint64 length (LE)``,
``uint32 masked_crc32c(length bytes)``, ``length`` bytes of payload, ``uint32
masked_crc32c(payload)`` (docs/release_format.md §1.1). The release gzips whole files (every family
but RWRL); the reader sniffs the gzip magic ``1F 8B`` rather than trusting a file name.

Reading streams in constant memory: the file is inflated in chunks of ``CHUNK`` bytes (or, for
one gzip member of at most ``rlu.data.inflate.WHOLE_GZIP_MAX`` inflated bytes, in one call of
libdeflate) and records are cut from each chunk in place, in batches of about ``CHUNK`` bytes;
only a record that straddles two chunks is copied to be joined. Both CRCs are verified by
default. Any damage (CRC mismatch, truncated record, cut or corrupt gzip stream) raises one
:class:`RecordError` naming the file and the byte offset of the record in the (decompressed)
record stream; ``on_error="skip"`` instead drops bad records, resynchronises on the next valid
header and counts what it skipped in :class:`ReadStats`.

The per-record Python work is small: one ``struct.unpack_from`` of the header and a dict lookup
of its length's CRC, one slice for the payload; the payload CRCs of a batch are one ``map`` of the
C-backed CRC-32C, masked and compared as an array. Runs of records of equal length
(control-suite and locomotion windows) are found as blocks: their headers compared as rows of a
strided view.
"""

from __future__ import annotations

import gzip
import io
import os
import queue
import struct
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import BinaryIO

import numpy as np

from rlu.files import move_into_place, open_private
from rlu.types import FormatError

GZIP_MAGIC = b"\x1f\x8b"
CHUNK = 1 << 22  # bytes of compressed input per read; memory stays O(CHUNK + largest record)
_MASK_DELTA = 0xA282EAD8
_HEADER = struct.Struct("<QI")
_U32 = struct.Struct("<I")
# A length header beyond this (128 MiB) is damage, not a record: the release's largest records
# (Atari episodes of up to 27,000 PNG frames, DMLab episodes, locomotion episodes with 64x64x3
# camera bytes per step) are tens of MB. It also bounds what one record can cost in memory.
MAX_RECORD_BYTES = 1 << 27


def _crc_impl() -> Callable[[bytes], int]:
    try:
        import google_crc32c
    except ImportError as e:  # pragma: no cover - the release extra installs it
        # named, so that the command line prints the extra's install line (rlu.cli.EXTRA_OF)
        raise ModuleNotFoundError(
            "reading RL Unplugged release files needs the C-backed CRC-32C: "
            "pip install 'rlu[release]' (google-crc32c)",
            name="google_crc32c",
        ) from e
    return google_crc32c.value


_crc32c: Callable[[bytes], int] | None = None


def _crc32c_fn() -> Callable[[bytes], int]:
    global _crc32c
    if _crc32c is None:
        _crc32c = _crc_impl()
    return _crc32c


def crc32c(data: bytes) -> int:
    """Plain CRC-32C (Castagnoli) of ``data``."""
    return _crc32c_fn()(data if isinstance(data, bytes) else bytes(data))


def mask(crc: int) -> int:
    """TFRecord's CRC mask: rotate right by 15 bits, add 0xA282EAD8 (mod 2^32)."""
    return ((((crc >> 15) | (crc << 17)) & 0xFFFFFFFF) + _MASK_DELTA) & 0xFFFFFFFF


def masked_crc32c(data: bytes) -> int:
    return mask(crc32c(data))


class RecordError(FormatError):
    """A damaged TFRecord file; the message names the file and the byte offset."""

    def __init__(self, path: str, offset: int, what: str, fix: str = ""):
        self.path = path
        self.offset = offset
        self.what = what
        hint = fix or (
            "the file is damaged: download it again (rlu download verifies sha256), or pass "
            "on_error='skip' (--skip-corrupt) to drop bad records"
        )
        super().__init__(f"{path}: {what} at byte offset {offset}; {hint}")


@dataclass
class ReadStats:
    """What a read saw: records returned, records skipped in ``on_error="skip"`` mode, and why."""

    records: int = 0
    skipped: int = 0
    errors: list[str] = field(default_factory=list)
    compressed: bool = False
    bytes_read: int = 0
    """Bytes of the decompressed record stream consumed."""


def is_gzip(path: str | os.PathLike) -> bool:
    with open(path, "rb") as f:
        return f.read(2) == GZIP_MAGIC


def _gzip_chunks(f: BinaryIO, path: str) -> Iterator[bytes | bytearray]:
    """Inflate a gzip file (one or more members) chunk by chunk; cut or corrupt streams raise.

    Every call to inflate is capped at ``CHUNK`` bytes of output (input it cannot take yet waits in
    ``unconsumed_tail``), so a bomb (gigabytes of zeros in a few MB) costs one chunk of memory at a
    time, never the whole inflated size. The offset in a raised error is the number of
    decompressed bytes produced before the damage.

    The inflater is the fastest installed (``rlu.data.inflate``): a file of one gzip member that
    inflates to at most ``WHOLE_GZIP_MAX`` bytes is inflated in one call of libdeflate (memory:
    that bound, twice at most), anything else streams through zlib-ng or zlib.
    """
    from rlu.data.inflate import WHOLE_GZIP_MAX, gunzip_whole, gzip_decompressobj, gzip_errors

    size = os.fstat(f.fileno()).st_size
    if 0 < size <= WHOLE_GZIP_MAX:  # one call of the fastest inflater
        whole = gunzip_whole(f.read(size + 1))  # the file's size: no 64 MiB buffer to shrink
        if whole is not None:
            yield whole  # framed in place, in batches of about CHUNK bytes
            return
        f.seek(0)  # several members, damage, or no libdeflate: the streaming path decides
    errors = gzip_errors()
    d = gzip_decompressobj()
    consumed = 0  # compressed bytes used so far
    produced = 0
    data = f.read(CHUNK)
    if not data:
        raise RecordError(path, 0, "empty file where a gzip stream was expected")
    at_end = False  # the file has no more bytes
    while True:
        if not data:
            data = f.read(CHUNK)
            at_end = not data
        try:
            out = d.decompress(data, CHUNK)
        except errors as e:
            raise RecordError(
                path,
                produced,
                f"corrupt gzip stream ({e}) near compressed byte {consumed}",
                "the download is damaged: fetch it again (rlu download re-verifies sha256)",
            ) from None
        consumed += len(data) - len(d.unconsumed_tail) - len(d.unused_data)
        if out:
            produced += len(out)
            yield out
        if d.eof:
            rest = d.unused_data or f.read(CHUNK)
            if not rest:
                return
            if rest[:2] == GZIP_MAGIC:  # another member (concatenated gzip files)
                d = gzip_decompressobj()
                data = rest
                continue
            while rest and not rest.strip(b"\0"):  # zero padding after the stream is harmless
                rest = f.read(CHUNK)
            if rest:
                raise RecordError(path, produced, "garbage after the end of the gzip stream")
            return
        data = d.unconsumed_tail
        if at_end and not out and not data:  # inflate wants input the file no longer has
            raise RecordError(
                path,
                produced,
                f"gzip stream cut after {consumed} compressed bytes (the file is truncated)",
                "the download is incomplete: fetch it again (rlu download resumes and verifies)",
            )


def _plain_chunks(f: BinaryIO) -> Iterator[bytes]:
    while True:
        raw = f.read(CHUNK)
        if not raw:
            return
        yield raw


def _prefetch(chunks: Iterator[bytes | bytearray], depth: int = 2) -> Iterator[bytes | bytearray]:
    """Run a chunk iterator in a thread, ``depth`` chunks ahead.

    zlib releases the GIL while it inflates, so the next chunk is inflated while this thread
    frames and decodes the current one. Errors are re-raised here, in order.
    """
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    done = object()

    def run() -> None:
        try:
            for c in chunks:
                while not stop.is_set():
                    try:
                        q.put(c, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put(done)
        except BaseException as e:  # handed to the consumer
            q.put(e)

    t = threading.Thread(target=run, name="rlu-inflate", daemon=True)
    t.start()
    try:
        while True:
            item = q.get()
            if item is done:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        t.join()


class RecordReader:
    """Streams the payloads of one TFRecord file (gzip or plain) with CRC checks.

    ``batches()`` yields lists of payloads (bytes), a chunk's worth at a time; ``__iter__`` yields
    payloads one by one. ``stats`` says what was read and skipped.

    ``max_record_bytes`` (at most :data:`MAX_RECORD_BYTES`) refuses a longer record at its header,
    before any of it is held: each family passes its own (``families.Family.max_record_bytes``),
    with ``limit_note`` saying why in the error.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        verify: bool = True,
        on_error: str = "raise",
        compression: str | None = None,
        prefetch: bool = False,
        max_record_bytes: int = MAX_RECORD_BYTES,
        limit_note: str = "",
    ):
        if on_error not in ("raise", "skip"):
            raise ValueError("on_error must be 'raise' or 'skip'")
        self.path = os.fspath(path)
        self.max_record_bytes = min(max_record_bytes, MAX_RECORD_BYTES)
        self.limit_note = limit_note or "the release's records are tens of MB at most"
        self.verify = verify
        self.skip = on_error == "skip"
        self.compression = compression
        self.prefetch = prefetch
        self.stats = ReadStats()
        self._len_crc: dict[int, int] = {}

    def __iter__(self) -> Iterator[bytes]:
        for batch in self.batches():
            yield from batch

    def _header_crc(self, length: int) -> int:
        """The masked CRC-32C of the header of a ``length``-byte record (kept for 4096 lengths)."""
        got = mask(crc32c(struct.pack("<Q", length)))
        if len(self._len_crc) < 4096:
            self._len_crc[length] = got
        return got

    def _bad(self, offset: int, what: str) -> None:
        if not self.skip:
            raise RecordError(self.path, offset, what)
        self.stats.skipped += 1
        self.stats.errors.append(f"{what} at byte offset {offset}")

    def batches(self) -> Iterator[list[bytes]]:
        for payloads, _ in self.batches_with_offsets():
            yield payloads

    def batches_with_offsets(self) -> Iterator[tuple[list[bytes], list[int]]]:
        """Like :meth:`batches`, with each record's byte offset in the (decompressed) stream."""
        with open(self.path, "rb") as f:
            magic = f.read(2)
            f.seek(0)
            gz = self.compression == "gzip" or (self.compression is None and magic == GZIP_MAGIC)
            self.stats.compressed = gz
            chunks = _gzip_chunks(f, self.path) if gz else _plain_chunks(f)
            if gz and self.prefetch:
                chunks = _prefetch(chunks)
            # a plain file's size bounds every record: a header claiming more fails at once
            total = None if gz else os.fstat(f.fileno()).st_size
            yield from self._frame(chunks, total)

    def _frame(
        self, chunks: Iterable[bytes | bytearray], total: int | None
    ) -> Iterator[tuple[list[bytes], list[int]]]:
        """Cut records from the inflated chunks without re-copying them.

        ``buf[pos:]`` is what is not consumed yet. A chunk is framed in place; the only bytes
        copied are a record that straddles two chunks (joined with the start of the next, or,
        for a record longer than a chunk, with all the chunks it spans, once, when it is whole).
        """
        buf: bytes | bytearray = b""
        pos = 0  # first byte of buf not consumed
        base = 0  # stream offset of buf[0]
        skipping = False  # resynchronising after a bad header
        cut: RecordError | None = None
        it = iter(chunks)
        final = False
        need = 0  # bytes buf[pos:] must hold before a record can be cut from it
        parts: list[bytes | bytearray] = []  # chunks held back until a long record is complete
        held = 0
        while not final:
            try:
                new = next(it)
            except StopIteration:
                new, final = b"", True
            except RecordError as e:  # a cut or corrupt gzip stream: frame what was inflated
                new, final, cut = b"", True, e
            rest = len(buf) - pos
            if not final and rest + held + len(new) < need:
                parts.append(new)  # joined once when the record is whole: no quadratic copies
                held += len(new)
                continue
            if not rest and not parts:
                base += len(buf)
                buf, pos = new, 0
            else:
                k = 0 if parts or skipping or final else self._straddle(buf, pos, new)
                if k:  # the leftover and new[:k] are exactly one record: frame it alone
                    head = b"".join([memoryview(buf)[pos:], memoryview(new)[:k]])
                    base += pos
                    got = self._cut(head, 0, base, False, False, None, total)
                    out, offsets, hpos, skipping, need, _ = got
                    if out:
                        self.stats.records += len(out)
                        self.stats.bytes_read = base + hpos
                        yield out, offsets
                    if hpos == len(head) and not skipping:
                        base += len(head) - k
                        buf, pos = new, k
                    else:  # damage in skip mode: frame the rest of head with new
                        buf, pos = b"".join([memoryview(head)[hpos:], memoryview(new)[k:]]), 0
                        base += hpos
                else:
                    base += pos
                    buf = b"".join([memoryview(buf)[pos:], *parts, new])
                    pos = 0
                    parts, held = [], 0
            more = True
            while more:
                out, offsets, pos, skipping, need, more = self._cut(
                    buf, pos, base, skipping, final, cut, total
                )
                self.stats.bytes_read = base + pos
                if out:
                    self.stats.records += len(out)
                    yield out, offsets

    def _straddle(self, buf: bytes | bytearray, pos: int, new: bytes | bytearray) -> int:
        """How many bytes of ``new`` complete the record begun at ``buf[pos:]``; 0 when that is
        not plain (the header is not in buf and new together, or is implausible, or the record
        goes on past new): the caller then joins the two and lets :meth:`_cut` decide."""
        rest = len(buf) - pos
        header = bytes(buf[pos : pos + 12])
        if rest < 12:
            header += bytes(new[: 12 - rest])
            if len(header) < 12:
                return 0
        (length,) = struct.unpack_from("<Q", header)
        if length > self.max_record_bytes:
            return 0
        k = length + 16 - rest
        return k if 0 < k <= len(new) else 0

    def _cut(
        self,
        buf: bytes | bytearray,
        pos: int,
        base: int,
        skipping: bool,
        final: bool,
        cut: RecordError | None,
        total: int | None,
    ) -> tuple[list[bytes], list[int], int, bool, int, bool]:
        """Cut complete records from ``buf[pos:]``, about ``CHUNK`` bytes of them: (payloads,
        their offsets, the new pos, skipping, bytes ``buf[pos:]`` needs before the next record is
        whole, whether it stopped at the batch's size with more records to cut).

        The headers are walked with one ``unpack_from`` a record (a run of equal headers is
        taken as a block: the headers compared as rows of a strided view); the payload CRCs are
        computed in one ``map`` and compared, masked, as an array.
        """
        out: list[bytes] = []
        offsets: list[int] = []
        n = len(buf)
        end = pos + CHUNK  # this batch's size
        verify = self.verify
        limit = self.max_record_bytes
        unpack = _HEADER.unpack_from
        known = self._len_crc
        u: np.ndarray | None = None  # buf as uint8, made when first needed
        need = 0
        more = False
        while True:
            if skipping:
                o = _find_header(buf, pos, n - 12, limit)
                if o < 0:
                    # keep the last 11 bytes: a header may straddle the chunk boundary
                    pos = n if final else max(pos, n - 11)
                    break
                pos = o
                skipping = False
            starts: list[int] = []  # records found, their start in buf
            lengths: list[int] = []
            stop = ""  # why the walk stopped at pos, when it is damage
            prev, same = -1, 0  # the last length, how many records in a row had it
            while True:
                if n - pos < 12:
                    need = 12
                    break
                length, hcrc = unpack(buf, pos)
                if verify and hcrc != (known.get(length) or self._header_crc(length)):
                    stop = "length CRC mismatch (corrupt record header)"
                    break
                if length > limit:
                    stop = (
                        f"record length {length:,} bytes is over the limit of "
                        f"{limit:,} ({self.limit_note})"
                    )
                    break
                stride = length + 16
                if pos + stride > n:
                    if total is not None and base + pos + stride > total:
                        stop = (
                            f"truncated record (its header says {length} payload bytes; "
                            f"{total - base - pos - 12} bytes of payload and CRC remain)"
                        )
                    else:
                        need = stride
                    break
                starts.append(pos)
                lengths.append(length)
                pos += stride
                if pos >= end:
                    more = True
                    break
                if length != prev:
                    prev, same = length, 0
                    continue
                same += 1
                rows = min((n - pos) // stride, (end - pos) // stride + 1)
                if same < 8 or rows < 16:
                    continue
                # a run of equal lengths (control-suite windows): the next headers equal to the
                # last one (already checked) are records too, found as a block
                same = 0
                if u is None:
                    u = np.frombuffer(buf, np.uint8)
                last = u[pos - stride : pos - stride + 12]
                probe = min(rows, 64)  # a short run costs 64 rows, not the whole buffer
                eq = (u[pos : pos + probe * stride].reshape(probe, stride)[:, :12] == last).all(1)
                if eq.all() and rows > probe:
                    block = u[pos : pos + rows * stride].reshape(rows, stride)[:, :12]
                    eq = (block == last).all(1)
                run = len(eq) if eq.all() else int(np.argmin(eq))
                if run:
                    if starts:  # the records before the block, in order
                        self._payloads(buf, u, starts, lengths, base, out, offsets)
                        starts, lengths = [], []
                    self._block(u, pos, run, length, base, out, offsets)
                    pos += run * stride
                    if pos >= end:
                        more = True
                        break
            if starts:
                if u is None:
                    u = np.frombuffer(buf, np.uint8)
                self._payloads(buf, u, starts, lengths, base, out, offsets)
            if not stop:
                break
            self._bad(base + pos, stop)  # raises in the default mode
            skipping = True
            pos += 1
            more = False
        if more:
            return out, offsets, pos, skipping, 0, True
        if final and pos < n and not skipping:
            rest = buf[pos:]
            if len(rest) >= 12:
                (length,) = struct.unpack_from("<Q", rest)
                what = (
                    f"truncated record (its header says {length} payload bytes; "
                    f"{len(rest) - 12} bytes of payload and CRC remain)"
                )
            else:
                what = f"truncated record header ({len(rest)} of 12 bytes)"
            if cut is not None:
                what = f"{what}: {cut.what}"
            self._bad(base + pos, what)
            pos = n
        elif final and cut is not None:
            self._bad(base + pos, cut.what)
            self.stats.skipped -= 1  # no record was lost, only the stream's end
        return out, offsets, pos, skipping, need, False

    def _block(
        self,
        u: np.ndarray,
        pos: int,
        run: int,
        length: int,
        base: int,
        out: list[bytes],
        offsets: list[int],
    ) -> None:
        """Append the ``run`` records of ``length`` bytes at ``u[pos:]`` (their headers checked)
        to ``out``: their payloads copied out as one block, then sliced from it as bytes."""
        stride = length + 16
        rows = u[pos : pos + run * stride].reshape(run, stride)
        if length:
            joined = rows[:, 12 : 12 + length].tobytes()
            payloads = [joined[i : i + length] for i in range(0, run * length, length)]
        else:
            payloads = [b""] * run
        where = list(range(base + pos, base + pos + run * stride, stride))
        if self.verify and length and run >= _BLOCK_CRC_RUN:
            want = rows[:, 12 + length :].copy().view("<u4")[:, 0]
            if _crc32c_fn()(joined) == _combined(_unmask(want), length):
                out.extend(payloads)  # every payload's CRC holds (see _combined)
                offsets.extend(where)
                return
        if self.verify:  # each payload checked on its own: the bad ones found and reported
            got = np.fromiter(map(_crc32c_fn(), payloads), np.uint32, run)
            got = ((got >> np.uint32(15)) | (got << np.uint32(17))) + np.uint32(_MASK_DELTA)
            want = rows[:, 12 + length :].copy().view("<u4")[:, 0]
            bad = np.flatnonzero(got != want)
            if bad.size:
                payloads, where = self._drop(payloads, where, bad)
        out.extend(payloads)
        offsets.extend(where)

    def _drop(
        self, payloads: list[bytes], where: list[int], bad: np.ndarray
    ) -> tuple[list[bytes], list[int]]:
        """``payloads`` and ``where`` without the records at ``bad`` (payload CRC mismatches),
        each reported: the first raises in the default mode."""
        for i in bad.tolist():
            self._bad(where[i], "payload CRC mismatch")
        keep = np.ones(len(payloads), bool)
        keep[bad] = False
        k = keep.tolist()
        return (
            [q for q, ok in zip(payloads, k, strict=True) if ok],
            [o for o, ok in zip(where, k, strict=True) if ok],
        )

    def _payloads(
        self,
        buf: bytes | bytearray,
        u: np.ndarray,
        starts: list[int],
        lengths: list[int],
        base: int,
        out: list[bytes],
        offsets: list[int],
    ) -> None:
        """Append the payloads of the records at ``starts`` (and their stream offsets) to
        ``out`` (and ``offsets``), each payload CRC checked when verifying."""
        if isinstance(buf, bytes):
            payloads = [buf[s + 12 : s + 12 + n] for s, n in zip(starts, lengths, strict=True)]
        else:
            view = memoryview(buf)
            payloads = [
                view[s + 12 : s + 12 + n].tobytes() for s, n in zip(starts, lengths, strict=True)
            ]
        at = np.array(starts, np.int64)
        where = (at + base).tolist()
        if self.verify:
            got = np.fromiter(map(_crc32c_fn(), payloads), np.uint32, len(payloads))
            got = ((got >> np.uint32(15)) | (got << np.uint32(17))) + np.uint32(_MASK_DELTA)
            tail = at + 12 + np.array(lengths, np.int64)
            want = u[tail[:, None] + np.arange(4)].view("<u4")[:, 0]
            bad = np.flatnonzero(got != want)
            if bad.size:
                payloads, where = self._drop(payloads, where, bad)
        out.extend(payloads)
        offsets.extend(where)


_CRC_TABLE: np.ndarray | None = None
_BLOCK_CRC_RUN = 64  # a run of this many equal records or more is checked by one CRC call
_SHIFTS: dict[int, np.ndarray] = {}  # bytes -> byte tables of the shift operator (_shift_tables)


def _unmask(masked: np.ndarray) -> np.ndarray:
    """The CRC-32C values of TFRecord's masked CRCs (:func:`mask` undone)."""
    r = (masked - np.uint32(_MASK_DELTA)).astype(np.uint32)
    return ((r >> np.uint32(17)) | (r << np.uint32(15))).astype(np.uint32)


def _shift_tables(nbytes: int) -> np.ndarray:
    """Byte tables ``T`` (4 x 256) of the linear map ``f`` that advances a raw (unconditioned)
    reflected CRC-32C register over ``nbytes`` zero bytes: ``f(x) = T[0][x & 255] ^ T[1][x >> 8
    & 255] ^ T[2][x >> 16 & 255] ^ T[3][x >> 24]``."""
    tables = _SHIFTS.get(nbytes)
    if tables is None:
        table = _crc_table()
        basis = (np.uint32(1) << np.arange(32, dtype=np.uint32)).astype(np.uint32)
        if nbytes == 1:
            image = table[basis & np.uint32(0xFF)] ^ (basis >> np.uint32(8))
        else:  # f over n bytes is f over n // 2 bytes twice (and one byte more when n is odd)
            half = _shift_tables(nbytes // 2)
            image = _apply(half, _apply(half, basis))
            if nbytes % 2:
                image = _apply(_shift_tables(1), image)
        bits = ((np.arange(256)[:, None] >> np.arange(8)) & 1).astype(bool)  # (256, 8)
        tables = np.zeros((4, 256), np.uint32)
        for b in range(4):
            for k in range(8):
                tables[b][bits[:, k]] ^= image[8 * b + k]
        _SHIFTS[nbytes] = tables
    return tables


def _apply(tables: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The map of :func:`_shift_tables` applied to every value of ``x``."""
    return (
        tables[0][x & np.uint32(0xFF)]
        ^ tables[1][(x >> np.uint32(8)) & np.uint32(0xFF)]
        ^ tables[2][(x >> np.uint32(16)) & np.uint32(0xFF)]
        ^ tables[3][x >> np.uint32(24)]
    )


def _combined(crcs: np.ndarray, length: int) -> int:
    """The CRC-32C of ``n`` payloads of ``length`` bytes laid end to end, from their own CRCs.

    CRC-32C (initial value and final xor 0xFFFFFFFF) satisfies ``crc(A + B) = f_|B|(crc(A)) ^
    crc(B)``, with ``f_n`` the linear shift of :func:`_shift_tables` (zlib's ``crc32_combine``),
    so the payloads' CRCs combine pairwise in a tree, ``log2 n`` vectorised levels. When it equals
    the CRC of the payloads joined (one call over the block), every stored CRC is the payload's
    own, unless errors in several payloads cancel exactly, which CRC-32 detection of the block
    as one message rules out as for any one longer message (a chance of 2^-32 for random damage);
    on any difference each payload is checked on its own and the bad ones reported.
    """
    c = crcs.astype(np.uint32)
    n = 1 << max(0, (len(c) - 1).bit_length())
    c = np.concatenate([np.zeros(n - len(c), np.uint32), c])  # crc(b"") = 0 leads: f(0) = 0
    span = length
    while len(c) > 1:
        c = _apply(_shift_tables(span), c[0::2]) ^ c[1::2]
        span *= 2
    return int(c[0])


_SCAN = 1 << 20  # candidate offsets examined per numpy pass when resynchronising


def _crc_table() -> np.ndarray:
    """The byte table of reflected CRC-32C (Castagnoli polynomial 0x82F63B78)."""
    global _CRC_TABLE
    if _CRC_TABLE is None:
        t = np.arange(256, dtype=np.uint32)
        for _ in range(8):
            t = np.where(t & 1, (t >> 1) ^ np.uint32(0x82F63B78), t >> 1).astype(np.uint32)
        _CRC_TABLE = t
    return _CRC_TABLE


def _find_header(
    buf: bytes | bytearray, start: int, last: int, limit: int = MAX_RECORD_BYTES
) -> int:
    """First offset o in [start, last] where ``buf[o:o+8]`` is a length <= ``limit`` and
    ``buf[o+8:o+12]`` its masked CRC-32C; -1 if none.

    Vectorised: the cheap necessary conditions first (a length up to 2^27 has its top four bytes
    clear, and a header's CRC bytes are not all zero: one header in 2^32 has such a CRC, and its
    record is then skipped), then the CRC of the few remaining 8-byte windows at once (8 table
    steps). Resynchronising through megabytes of damage, or a bomb of zeros, is a few numpy
    passes, not a Python loop per byte.
    """
    if last < start:
        return -1
    u = np.frombuffer(buf, np.uint8)
    table = _crc_table()
    top = (limit.bit_length() + 7) // 8  # bytes of the length that may be non-zero
    for a in range(start, last + 1, _SCAN):
        n = min(_SCAN, last + 1 - a)
        high = np.zeros(n, np.uint8)
        for j in range(top, 8):
            high |= u[a + j : a + j + n]
        crc_bytes = np.zeros(n, np.uint8)
        for j in range(8, 12):
            crc_bytes |= u[a + j : a + j + n]
        cand = np.flatnonzero((high == 0) & (crc_bytes != 0))
        if not cand.size:
            continue
        rows = a + cand[:, None] + np.arange(12)
        win = u[rows]  # (candidates, 12)
        crc = np.full(len(cand), 0xFFFFFFFF, np.uint32)
        for j in range(8):
            crc = table[(crc ^ win[:, j]) & 0xFF] ^ (crc >> np.uint32(8))
        crc ^= np.uint32(0xFFFFFFFF)
        masked = ((crc >> np.uint32(15)) | (crc << np.uint32(17))) + np.uint32(_MASK_DELTA)
        stored = np.ascontiguousarray(win[:, 8:12]).view("<u4")[:, 0]
        length = np.ascontiguousarray(win[:, :8]).view("<u8")[:, 0]
        hit = np.flatnonzero((masked == stored) & (length <= limit))
        if hit.size:
            return a + int(cand[hit[0]])
    return -1


def read_records(
    path: str | os.PathLike, *, verify: bool = True, on_error: str = "raise"
) -> Iterator[bytes]:
    """Every payload of a TFRecord file, in order (gzip sniffed)."""
    return iter(RecordReader(path, verify=verify, on_error=on_error))


def frame(payload: bytes) -> bytes:
    """One framed record."""
    header = struct.pack("<Q", len(payload))
    return b"".join(
        (
            header,
            _U32.pack(masked_crc32c(header)),
            payload,
            _U32.pack(masked_crc32c(payload)),
        )
    )


class RecordWriter:
    """Writes framed records; ``compression="gzip"`` wraps the whole file in one gzip member.

    Writes go to ``path + ".partial"`` and are renamed into place on a clean close, so a failed
    write leaves no file under the final name.
    """

    def __init__(self, path: str | os.PathLike, compression: str | None = "gzip", level: int = 6):
        self.path = os.fspath(path)
        self._tmp = self.path + ".partial"
        # never through a link planted at the temporary name
        raw = os.fdopen(open_private(self._tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), "wb")
        self._raw = raw
        if compression == "gzip":
            # mtime=0 keeps the bytes reproducible; one member, as TF writes it.
            self._f: io.BufferedIOBase = gzip.GzipFile(
                fileobj=raw, mode="wb", compresslevel=level, mtime=0
            )
        elif compression in (None, "", "none"):
            self._f = raw
        else:
            raise ValueError(f"unknown compression {compression!r}; use 'gzip' or None")

    def write(self, payload: bytes) -> None:
        self._f.write(frame(payload))

    def close(self) -> None:
        if self._f is not self._raw:
            self._f.close()
        self._raw.close()
        move_into_place(self._tmp, self.path)

    def abort(self) -> None:
        try:
            if self._f is not self._raw:
                self._f.close()
            self._raw.close()
        finally:
            if os.path.exists(self._tmp):
                os.remove(self._tmp)

    def __enter__(self) -> RecordWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_records(
    path: str | os.PathLike, payloads: Iterable[bytes], compression: str | None = "gzip"
) -> None:
    with RecordWriter(path, compression=compression) as w:
        for p in payloads:
            w.write(p)
