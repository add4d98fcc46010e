"""PNG frames: the direct-decoder fast path equals Image.open; our encoder round-trips."""

from __future__ import annotations

import io

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from rlu.codecs import png
from rlu.types import FormatError


def _pillow_png(img: np.ndarray, **kw) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", **kw)
    return buf.getvalue()


@pytest.mark.parametrize("shape", [(84, 84), (72, 96, 3), (5, 7)])
def test_fast_path_equals_image_open(shape):
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, shape, dtype=np.uint8)
    smooth = np.cumsum(np.ones(shape, np.uint8), axis=0, dtype=np.uint8)
    for img in (noise, smooth, np.zeros(shape, np.uint8)):
        data = _pillow_png(img)  # Pillow picks filters adaptively (Sub, Up, Paeth, ...)
        fast = png._fast_decode(data, png._pil())
        assert fast is not None and np.array_equal(fast, img)
        assert np.array_equal(png.decode_png(data), np.asarray(Image.open(io.BytesIO(data))))
        assert np.array_equal(png.decode_png(png.encode_png(img)), img)


def test_other_pngs_fall_back_to_image_open():
    img = np.arange(64, dtype=np.uint8).reshape(8, 8)
    pal = Image.fromarray(img).convert("P")
    buf = io.BytesIO()
    pal.save(buf, format="PNG")
    assert png._fast_decode(buf.getvalue(), png._pil()) is None
    assert png.decode_png(buf.getvalue(), channels=1).shape == (8, 8)
    inter = io.BytesIO()
    Image.fromarray(img).save(inter, format="PNG", interlace=1)
    assert np.array_equal(png.decode_png(inter.getvalue()), img)


def test_damaged_png_is_a_format_error():
    data = _pillow_png(np.random.default_rng(1).integers(0, 256, (84, 84), dtype=np.uint8))
    with pytest.raises(FormatError):
        png.decode_png(data[: len(data) // 2])
    with pytest.raises(FormatError):
        png.decode_png(b"GIF89a....")


@settings(max_examples=200, deadline=None)
@given(flips=st.lists(st.tuples(st.integers(8, 5000), st.integers(1, 255)), min_size=1, max_size=3))
def test_fuzz_mutated_png(flips):
    data = bytearray(_pillow_png(np.arange(84 * 84, dtype=np.uint8).reshape(84, 84)))
    for pos, x in flips:
        data[pos % len(data)] ^= x
    try:
        png.decode_png(bytes(data), channels=1)
    except FormatError:
        pass
