"""PNG frames of the release: 84x84 grey (Atari) and 72x96x3 BGR (DMLab).

Decoding uses Pillow (the ``release`` extra), imported on first use. The release's Atari PNGs use
the Paeth filter (the TF-written fixture holds Sub, Up and Paeth rows), whose per-pixel recurrence
a numpy decoder cannot vectorise, so the decoder is Pillow's C one, called directly for 8-bit grey
and RGB frames (``_fast_decode``) rather than through ``Image.open``, whose Python-side plugin and
chunk handling dominates on 84x84 frames (``bench/release_reader.py --png``; the figures:
bench/README.md, "Design choices").
Anything else (palette, 16-bit, interlaced) goes through ``Image.open``.

Encoding (for writing test shards and round trips) is a few lines of zlib with filter 0: no
dependency, and any PNG reader accepts it.
"""

from __future__ import annotations

import io
import struct
import zlib
from types import ModuleType

import numpy as np

from rlu.types import FormatError

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_Image: ModuleType | None = None


def _pil() -> ModuleType:
    global _Image
    if _Image is None:
        try:
            from PIL import Image
        except ImportError as e:
            raise ModuleNotFoundError(
                "decoding the release's PNG frames needs Pillow: pip install 'rlu[release]'",
                name="PIL",
            ) from e
        Image.MAX_IMAGE_PIXELS = max(Image.MAX_IMAGE_PIXELS or 0, 1 << 26)
        _Image = Image
    return _Image


_FAST_MODES = {0: ("L", 1), 2: ("RGB", 3)}  # PNG colour type -> (Pillow mode, channels)


def _fast_decode(data: bytes, Image: ModuleType) -> np.ndarray | None:
    """8-bit grey / RGB, non-interlaced: Pillow's C inflate + unfilter without ``Image.open``.

    ``Image.open`` spends most of its time in Python (plugin lookup, chunk parsing); calling the
    same C decoder directly is faster on 84x84 frames (bench/README.md). Anything else returns
    None and goes through ``Image.open``.
    """
    pos, n = 8, len(data)
    idat = []
    ihdr = None
    while pos + 8 <= n:
        length, kind = struct.unpack_from(">I4s", data, pos)
        body = data[pos + 8 : pos + 8 + length]
        if len(body) != length:
            return None
        if kind == b"IHDR":
            ihdr = struct.unpack_from(">IIBBBBB", body) if length == 13 else None
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
        pos += 12 + length
    if ihdr is None or not idat:
        return None
    w, h, depth, color, _, _, interlace = ihdr
    if depth != 8 or interlace or color not in _FAST_MODES or not 0 < w * h <= 1 << 26:
        return None
    mode, channels = _FAST_MODES[color]
    im = Image.core.new(mode, (w, h))
    dec = Image._getdecoder(mode, "zip", (mode, 0))
    dec.setimage(im, (0, 0, w, h))
    status, err = dec.decode(b"".join(idat))
    if err < 0 or status >= 0:  # status < 0: the image is complete
        return None
    enc = Image._getencoder(mode, "raw", (mode, 0, 1))
    enc.setimage(im, (0, 0, w, h))
    _, _, raw = enc.encode(w * h * channels + 64)
    if len(raw) != w * h * channels:
        return None
    arr = np.frombuffer(raw, np.uint8)
    return arr.reshape(h, w) if channels == 1 else arr.reshape(h, w, channels)


def decode_png(
    data: bytes, channels: int | None = None, size: tuple[int, int] | None = None
) -> np.ndarray:
    """One PNG -> uint8 array (H, W) for grey, (H, W, C) otherwise, as stored (no reordering).

    ``channels=1`` insists on a grey image (as the original loaders' ``decode_png(channels=1)``).
    ``size`` (H, W): refuse any other size from the header, before a pixel is decoded (a PNG
    declaring 65536x65536 costs nothing).
    """
    if not data.startswith(PNG_MAGIC):
        raise FormatError(f"not a PNG image (starts with {bytes(data[:8])!r})")
    if size is not None:
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise FormatError("damaged PNG image: no IHDR chunk first")
        w, h = struct.unpack_from(">II", data, 16)
        if (h, w) != tuple(size):
            raise FormatError(
                f"PNG image of {w}x{h} pixels; the release's frames are {size[1]}x{size[0]}"
            )
    Image = _pil()
    try:
        arr = _fast_decode(data, Image)
    except Exception:  # damaged data: let Image.open produce the error message
        arr = None
    if arr is not None and (channels is None or (arr.ndim == 2) == (channels == 1)):
        return arr
    try:
        im = Image.open(io.BytesIO(data), formats=("PNG",))
        im.load()
    except Exception as e:  # Pillow raises several types for damaged images
        raise FormatError(f"damaged PNG image: {e}") from None
    if channels == 1 and im.mode != "L":
        im = im.convert("L")
    elif channels == 3 and im.mode != "RGB":
        im = im.convert("RGB")
    return np.asarray(im)


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def encode_png(img: np.ndarray, level: int = 6) -> bytes:
    """uint8 (H, W) grey or (H, W, 3) colour -> PNG bytes (8-bit, filter 0)."""
    img = np.ascontiguousarray(img, np.uint8)
    if img.ndim == 2:
        color = 0
        h, w = img.shape
        rows = img
    elif img.ndim == 3 and img.shape[2] in (3, 4):
        color = 2 if img.shape[2] == 3 else 6
        h, w = img.shape[:2]
        rows = img.reshape(h, -1)
    else:
        raise ValueError(f"cannot write a PNG of shape {img.shape}; use (H, W) or (H, W, 3)")
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], axis=1).tobytes()
    ihdr = struct.pack(">IIBBBBB", w, h, 8, color, 0, 0, 0)
    return (
        PNG_MAGIC
        + _chunk(b"IHDR", ihdr)
        + _chunk(b"IDAT", zlib.compress(raw, level))
        + (_chunk(b"IEND", b""))
    )
