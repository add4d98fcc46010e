"""The inflaters: libdeflate and zlib-ng give zlib's bytes; every inflater refuses what zlib's
path refuses (wrong sizes, bombs, trailing bytes); the frame column reads rows in any order and
with repeats; the release's gzip shards inflate the same whole or streamed."""

from __future__ import annotations

import gzip
import zlib

import numpy as np
import pytest

from rlu.data import DatasetWriter, Schema, inflate, make_episode, open_dataset
from rlu.data.release.framing import RecordReader, write_records
from rlu.types import ArraySpec, DiscreteSpec, FormatError

ALL = inflate.installed()
N = 84 * 84


def frames(n: int, seed: int = 0) -> np.ndarray:
    """Frames with the structure of game screens: flat regions, a few sprites, noise."""
    rng = np.random.default_rng(seed)
    out = np.zeros((n, 84, 84), np.uint8)
    out[:, 60:, :] = 90
    for i in range(n):
        y, x = rng.integers(0, 76, 2)
        out[i, y : y + 8, x : x + 8] = rng.integers(0, 256)
        out[i] ^= (rng.random((84, 84)) < 0.02).astype(np.uint8) * 7
    return out


def test_the_fast_inflaters_are_installed_here():
    """The dev extra installs them: this checks their bytes, not only zlib's fallback."""
    assert ALL == ("libdeflate", "zlib")
    assert inflate.gzip_inflater() == "zlib-ng"


@pytest.mark.parametrize("name", ALL)
def test_frames_inflate_to_zlibs_bytes(name):
    f = frames(50)
    blobs = [zlib.compress(x.tobytes(), level) for x, level in zip(f, [1, 6, 9] * 17, strict=False)]
    data = b"".join(blobs)
    ends = np.cumsum([len(b) for b in blobs])
    out = np.empty((50, 84, 84), np.uint8)
    with inflate.use(name):
        assert inflate.inflate_frames(data, ends - [len(b) for b in blobs], ends, out, N) is None
        assert np.array_equal(out, f)
        # rows placed where asked
        placed = np.zeros((60, 84, 84), np.uint8)
        rows = np.random.default_rng(1).permutation(60)[:50]
        starts = ends - [len(b) for b in blobs]
        assert inflate.inflate_frames(data, starts, ends, placed, N, rows) is None
        assert np.array_equal(placed[rows], f)


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize(
    "blob, why",
    [
        (b"not a zlib stream at all", "zlib"),
        (zlib.compress(bytes(N - 1)), "size"),
        (zlib.compress(bytes(6 << 20), 9), "size"),  # a bomb: 6 MiB where 7 KB belong
        (zlib.compress(bytes(N)) + b"tail", "after the end"),
        (zlib.compress(bytes(N))[:-1], ""),  # cut
    ],
    ids=["garbage", "short", "bomb", "trailing", "cut"],
)
def test_every_inflater_refuses_a_bad_frame(name, blob, why):
    good = zlib.compress(bytes(N))
    data = good + blob
    out = np.empty((2, N), np.uint8)
    with inflate.use(name):
        bad = inflate.inflate_frames(data, np.array([0, len(good)]), np.array([len(good),
                                     len(data)]), out, N)  # fmt: skip
    assert bad is not None and bad[0] == 1


def test_env_var_and_use_refuse_unknown_inflaters(monkeypatch):
    monkeypatch.setenv("RLU_INFLATER", "snappy")
    with pytest.raises(Exception, match="use one of"):
        inflate._choose()
    monkeypatch.setenv("RLU_INFLATER", "zlib")
    assert inflate._choose() == "zlib"
    with pytest.raises(Exception, match="not installed"):
        with inflate.use("brotli"):
            pass


@pytest.mark.parametrize("name", ALL)
def test_the_frame_column_reads_any_rows_once(tmp_path, name):
    schema = Schema(ArraySpec((84, 84), "uint8"), DiscreteSpec((), "int64", 4), frame_stack=4,
                    image_encoding="zlib")  # fmt: skip
    f = frames(300, seed=2)
    with DatasetWriter(tmp_path / "ds", schema) as w:
        for a, b in ((0, 120), (120, 300)):
            w.append(make_episode(f[a:b], np.zeros(b - a - 1, np.int64), np.zeros(b - a - 1),
                                  True))  # fmt: skip
    col = open_dataset(tmp_path / "ds").column("observation")
    ref = np.concatenate([np.zeros((3, 84, 84), np.uint8), f[:120], np.zeros((3, 84, 84),
                          np.uint8), f[120:]])  # fmt: skip
    rng = np.random.default_rng(0)
    with inflate.use(name):
        for rows in (rng.integers(0, len(col), (64, 5)), np.arange(len(col)),
                     rng.integers(0, len(col), 7), np.array([5, 5, 5, 2])):  # fmt: skip
            assert np.array_equal(col.take(rows), ref[rows])
        assert np.array_equal(col[10:200:3], ref[10:200:3])
        with pytest.raises(IndexError):
            col.take(np.array([len(col)]))


def test_a_bad_frame_names_file_and_row_with_threads(tmp_path):
    schema = Schema(ArraySpec((84, 84), "uint8"), DiscreteSpec((), "int64", 4), frame_stack=4,
                    image_encoding="zlib")  # fmt: skip
    with DatasetWriter(tmp_path / "ds", schema) as w:
        w.append(make_episode(frames(400), np.zeros(399, np.int64), np.zeros(399), True))
    zpath = tmp_path / "ds" / "steps" / "observation.zlib"
    offsets = np.fromfile(tmp_path / "ds" / "steps" / "observation.offsets.bin", "<i8")
    data = bytearray(zpath.read_bytes())
    a = int(offsets[300])
    data[a + 2 : a + 12] = bytes(10)  # damage inside frame 300's stream
    zpath.write_bytes(bytes(data))
    col = open_dataset(tmp_path / "ds").column("observation")
    for name in ALL:
        with inflate.use(name), pytest.raises(FormatError, match="observation.zlib: frame 300 "):
            col.take(np.arange(len(col)))


def _shard(path, payloads, members=1, tail=b""):
    raw = path.with_suffix(".raw")
    write_records(raw, payloads, compression=None)
    body = raw.read_bytes()
    cut = np.linspace(0, len(body), members + 1).astype(int).tolist()
    parts = [gzip.compress(body[a:b], 1) for a, b in zip(cut[:-1], cut[1:], strict=True)]
    path.write_bytes(b"".join(parts) + tail)
    return path


@pytest.mark.parametrize("name", ALL)
def test_gzip_shards_read_the_same_whole_or_streamed(tmp_path, name):
    rng = np.random.default_rng(0)
    payloads = [rng.bytes(int(rng.integers(1, 3000))) for _ in range(300)]
    one = _shard(tmp_path / "one.gz", payloads)
    two = _shard(tmp_path / "two.gz", payloads, members=2)
    padded = _shard(tmp_path / "pad.gz", payloads, tail=bytes(100))
    with inflate.use(name):
        for path in (one, two, padded):
            assert list(RecordReader(path)) == payloads, path.name
        assert inflate.gunzip_whole(two.read_bytes()) is None  # several members: streamed
        assert inflate.gunzip_whole(padded.read_bytes()) is None
        whole = inflate.gunzip_whole(one.read_bytes())
        assert (whole is None) == (name == "zlib")
        assert inflate.gunzip_whole(one.read_bytes(), limit=1000) is None  # over the bound
        garbage = _shard(tmp_path / "garbage.gz", payloads, tail=b"junk")
        with pytest.raises(Exception, match="garbage after the end"):
            list(RecordReader(garbage))
