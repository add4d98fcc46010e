"""The fastest installed inflater, giving the same bytes as zlib, with zlib as the fallback.

Two kinds of input are inflated in rlu's hot paths:

- **frames**: the store's image columns keep one zlib stream per frame, each of a known size
  (``rlu.data.store.ZlibColumn``). :func:`inflate_frames` decodes many of them from one buffer
  into rows of an array, outside the GIL, with libdeflate (the ``deflate`` package) when it is
  installed, else with zlib;
- **gzip shards** of the original release (``rlu.data.release.framing``): a single gzip member
  whose trailer says it inflates to at most :data:`WHOLE_GZIP_MAX` bytes is inflated in one call
  by libdeflate (:func:`gunzip_whole`); longer shards stream through :func:`gzip_decompressobj`,
  zlib-ng's (the ``zlib-ng`` package) when installed, else zlib's.

Both packages are the ``inflate`` extra (``pip install "rlu[inflate]"``); ``bench/stream.py``
and ``bench/release_reader.py --inflate`` measure them against zlib on the same bytes. Inflating
is deterministic, so every inflater gives zlib's bytes for a valid stream. The guarantees on
hostile input hold with each of them: a frame inflates to exactly its declared size or is
refused, after allocating one frame (libdeflate writes into a buffer of that size and fails when
the stream would overflow it; zlib is capped at it); a stream with bytes after its end is
refused (zlib sees them; for libdeflate, which does not report how much input it used, the last
four bytes of the frame's stream must be the Adler-32 of the frame it made, which they are only
when the stream ends there, or when bytes were appended that end in that very checksum: the
frame is then the one the stream encodes).

``RLU_INFLATER=zlib`` (or :func:`use`) picks zlib even where libdeflate is installed.
"""

from __future__ import annotations

import contextlib
import os
import zlib
from collections.abc import Iterator
from typing import Any

import numpy as np

INFLATERS = ("libdeflate", "zlib")
"""Frame inflaters, fastest first."""
WHOLE_GZIP_MAX = 64 << 20
"""Largest gzip member (inflated bytes, from its trailer) :func:`gunzip_whole` inflates at once."""

try:  # the inflate extra
    import deflate as _libdeflate
except ImportError:  # pragma: no cover - exercised where the extra is absent
    _libdeflate = None  # type: ignore[assignment]  # None: the extra is absent
try:
    from zlib_ng import zlib_ng as _zlib_ng
except ImportError:  # pragma: no cover - exercised where the extra is absent
    _zlib_ng = None  # type: ignore[assignment]  # None: the extra is absent


def installed() -> tuple[str, ...]:
    """The frame inflaters importable here, fastest first (``zlib`` always)."""
    return tuple(n for n in INFLATERS if n == "zlib" or _libdeflate is not None)


def _choose() -> str:
    wanted = os.environ.get("RLU_INFLATER", "")
    if wanted:
        if wanted not in INFLATERS:
            from rlu.types import RluError

            raise RluError(f"RLU_INFLATER={wanted!r}; use one of {', '.join(INFLATERS)}")
        if wanted not in installed():
            from rlu.system import install_hint
            from rlu.types import RluError

            raise RluError(f"RLU_INFLATER={wanted}: not installed; {install_hint('inflate')}")
        return wanted
    return installed()[0]


_current = _choose()


def current() -> str:
    """The frame inflater in use (:data:`INFLATERS`)."""
    return _current


@contextlib.contextmanager
def use(name: str) -> Iterator[None]:
    """Inflate with ``name`` inside the block (tests and benches compare inflaters)."""
    global _current
    if name not in installed():
        from rlu.system import install_hint
        from rlu.types import RluError

        raise RluError(f"inflater {name!r} is not installed here; {install_hint('inflate')}")
    before, _current = _current, name
    try:
        yield
    finally:
        _current = before


def inflate_frames(
    data: Any,
    starts: np.ndarray,
    ends: np.ndarray,
    out: np.ndarray,
    nbytes: int,
    rows: np.ndarray | None = None,
) -> tuple[int, str] | None:
    """Inflate the zlib streams ``data[starts[j]:ends[j]]`` into rows of ``out`` (C-contiguous,
    ``nbytes`` bytes a row): stream j into row ``rows[j]`` (default: row j), each to exactly
    ``nbytes``. Returns None, or ``(j, why)`` for the first stream that is not one
    ``nbytes``-byte frame (the streams before j are written). The inflater releases the GIL on
    every frame, so threads decode in parallel."""
    view = memoryview(data)
    dest = out.data.cast("B")  # ndarray.data: the array's buffer, a memoryview
    s, e = starts.tolist(), ends.tolist()
    at = range(len(s)) if rows is None else rows.tolist()
    if _current == "libdeflate":
        inflate, adler = _libdeflate.zlib_decompress, _libdeflate.adler32
        error = _libdeflate.DeflateError
        for j in range(len(s)):
            blob = view[s[j] : e[j]]
            try:
                raw: bytes | bytearray = inflate(blob, nbytes)
            except error:
                return j, "not a zlib stream, or one that inflates past the frame's size"
            if len(raw) != nbytes:
                return j, f"inflates to {len(raw)} bytes"
            if int.from_bytes(blob[-4:], "big") != adler(raw):
                return j, "bytes after the end of its zlib stream"
            r = at[j]
            dest[r * nbytes : (r + 1) * nbytes] = raw
        return None
    for j in range(len(s)):
        d = zlib.decompressobj()
        try:
            raw = d.decompress(view[s[j] : e[j]], nbytes)
        except zlib.error as err:
            return j, str(err)
        if len(raw) != nbytes or not d.eof or d.unconsumed_tail:
            return j, "wrong size"
        if d.unused_data:
            return j, "bytes after the end of its zlib stream"
        r = at[j]
        dest[r * nbytes : (r + 1) * nbytes] = raw
    return None


# --- gzip streams (the release's shards) ------------------------------------------------------
def gzip_inflater() -> str:
    """The inflater :func:`gzip_decompressobj` uses: zlib-ng, else zlib."""
    return "zlib-ng" if _zlib_ng is not None and _current != "zlib" else "zlib"


def gzip_decompressobj() -> Any:
    """A streaming gzip inflater (``decompressobj(31)``): zlib-ng's when installed, else zlib's;
    the same interface (``decompress(data, max_length)``, ``eof``, ``unconsumed_tail``,
    ``unused_data``) and errors derived from ``zlib.error`` or :data:`gzip_errors`."""
    if gzip_inflater() == "zlib-ng":
        return _zlib_ng.decompressobj(31)
    return zlib.decompressobj(31)


def gzip_errors() -> tuple[type[BaseException], ...]:
    """The exceptions a corrupt stream raises from :func:`gzip_decompressobj`'s inflater."""
    if _zlib_ng is None:
        return (zlib.error,)
    # zlib_ng's stub declares `error: Exception`; at run time it is the exception class
    return (zlib.error, _zlib_ng.error)  # type: ignore[return-value]


def gunzip_whole(data: bytes, limit: int = WHOLE_GZIP_MAX) -> bytearray | None:
    """``data`` (a whole file) inflated in one call by libdeflate when it is exactly one gzip
    member inflating to at most ``limit`` bytes; None otherwise (several members, bytes after
    the member, a larger or damaged member, or no libdeflate): the caller then streams it, and
    the streaming path reports any damage. Memory: ``limit`` bytes at most."""
    if _libdeflate is None or _current == "zlib" or len(data) < 18 or data[:2] != b"\x1f\x8b":
        return None
    size = int.from_bytes(data[-4:], "little")  # ISIZE: the member's length mod 2**32
    if not 0 < size <= limit:
        return None
    try:
        out = _libdeflate.gzip_decompress(data, size)
    except _libdeflate.DeflateError:
        return None
    # libdeflate checked the CRC at the member's end; the file's last 8 bytes must be that very
    # trailer (one member, nothing after it), else the streaming path decides
    if len(out) != size or int.from_bytes(data[-8:-4], "little") != _libdeflate.crc32(out):
        return None
    return out
