"""The reader fuzz: mutated records of every family, each framed with a valid CRC (so the framing
lets it through to the decoder, the parser and the segment rules), must raise FormatError and
nothing else, with an explicit message (the record-level safety net, which turns a raw numpy or
Python error into a FormatError, must never be what catches them).

A seeded loop: 2,800 mutated records per family, 25,200 in all (a minute at most on a loaded
2-core machine); ``test_reader_fuzz_large`` (slow) runs ten times as many.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from rlu.codecs import example as E
from rlu.data.release import families as Fm
from rlu.data.release.framing import RecordWriter
from rlu.types import FormatError
from tests.release.test_families import _records, dmlab_record, window_record

# what a message looks like when the safety net caught a raw error (families._read)
RAW = re.compile(
    r"\((ValueError|IndexError|TypeError|KeyError|AssertionError|OverflowError|RecursionError|"
    r"ZeroDivisionError|AttributeError): "
)


def mutate_bytes(rng: np.random.Generator, p: bytes) -> bytes:
    """Bit flips, overwritten bytes, truncation, insertion, deletion or duplication."""
    b = bytearray(p)
    kind = int(rng.integers(0, 6))
    i = int(rng.integers(0, len(b) + 1))
    j = min(len(b), i + int(rng.integers(1, 50)))
    if kind == 0 and b:
        for _ in range(int(rng.integers(1, 5))):
            b[int(rng.integers(0, len(b)))] ^= 1 << int(rng.integers(0, 8))
    elif kind == 1 and b:
        for _ in range(int(rng.integers(1, 5))):
            b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
    elif kind == 2:
        del b[i:]
    elif kind == 3:
        b[i:i] = rng.integers(0, 256, int(rng.integers(1, 20)), dtype=np.uint8).tobytes()
    elif kind == 4:
        del b[i:j]
    else:
        b[i:i] = b[i:j]
    return bytes(b)


_EXTREMES_F = (np.nan, np.inf, -1e30, 2.0**62, 255.0, 3.0)
_EXTREMES_I = (2**62, -(2**62), -1, 0, 17)


def mutate_features(rng: np.random.Generator, feats: dict) -> dict:
    """A valid Example with a semantic defect: a feature dropped, emptied, lengthened,
    shortened, of another list type, replaced by bytes, an extreme value, a damaged PNG, or an
    unknown observation key."""
    f = {k: (list(v) if isinstance(v, list) else np.array(v)) for k, v in feats.items()}
    key = list(f)[int(rng.integers(0, len(f)))]
    v = f[key]
    op = int(rng.integers(0, 9))
    if op == 0:
        del f[key]
    elif op == 1:
        f[key] = [] if isinstance(v, list) else v[:0]
    elif op == 2:
        if isinstance(v, list):
            f[key] = v + v[:1]
        else:
            f[key] = np.concatenate([v, v[: int(rng.integers(1, 4))]]) if v.size else v
    elif op == 3:
        f[key] = v[:-1]
    elif op == 4:
        is_int = not isinstance(v, list) and v.dtype == np.int64
        f[key] = np.float32([1.5, 2.5]) if is_int else rng.integers(-5, 5, 3).astype(np.int64)
    elif op == 5:
        f[key] = [rng.integers(0, 256, int(rng.integers(0, 30)), dtype=np.uint8).tobytes()]
    elif op == 6 and not isinstance(v, list) and v.size:
        w = v.copy()
        pool = _EXTREMES_F if w.dtype.kind == "f" else _EXTREMES_I
        w.flat[int(rng.integers(0, w.size))] = pool[int(rng.integers(0, len(pool)))]
        f[key] = w
    elif op == 7 and isinstance(v, list) and v:
        i = int(rng.integers(0, len(v)))
        f[key] = v[:i] + [mutate_bytes(rng, v[i])] + v[i + 1 :]
    else:
        f[f"observation/x{int(rng.integers(0, 3))}"] = np.float32([1, 2, 3])
    return f


def _base_records(family: str, rng: np.random.Generator) -> list[dict]:
    """Valid records to mutate; images kept short and flat so PNG work does not dominate."""
    if family == "dm_locomotion_episodes":
        recs = [window_record(rng, t, {"walker/joints_pos": 5}, camera=True) for t in (2, 3)]
        for r in recs:
            r["episode_id"], r["timestamp"] = np.int64(3), np.int64(1234)
    elif family == "dmlab":
        recs = [dmlab_record(rng, t=2)]
    else:
        recs = _records(family, rng)[:4]
    for r in recs:
        for v in r.values():
            if isinstance(v, np.ndarray) and v.dtype == np.uint8:
                v //= 128
    return recs


def mutated_records(family: str, n: int, seed: int) -> list[bytes]:
    fam = Fm.get_family(family)
    payloads = [fam.encode(r) for r in _base_records(family, np.random.default_rng(seed))]
    rng = np.random.default_rng(seed + 1)
    out = []
    for _ in range(n):
        p = payloads[int(rng.integers(0, len(payloads)))]
        if rng.random() < 0.5:
            out.append(mutate_bytes(rng, p))
        else:
            out.append(E.encode_example(mutate_features(rng, E.decode_example(p))))
    return out


def _fuzz(tmp_path, family: str, n: int, seed: int) -> None:
    recs = mutated_records(family, n, seed)
    path = tmp_path / f"{family}-fuzz"
    with RecordWriter(path, compression=None) as w:  # plain: the reader sniffs, no gzip cost
        for r in recs:
            w.write(r)
    # skip mode: every record is read (alone where its batch fails); bad ones counted
    from rlu.data.release.framing import RecordReader

    rd = RecordReader(path, on_error="skip")
    good = sum(len(b) for b in Fm.iter_segments(path, family, reader=rd, on_error="skip"))
    assert rd.stats.records == n  # every record passed the framing (valid CRCs)
    assert 0 < rd.stats.skipped < n and good > 0, (rd.stats.skipped, good)
    raw = [m for m in rd.stats.errors if RAW.search(m)]
    assert not raw, f"{len(raw)} records needed the safety net, e.g. {raw[0]}"
    assert all("byte offset" in m for m in rd.stats.errors)
    # raise mode: the first bad record, as a FormatError naming the file, record and offset
    with pytest.raises(FormatError) as info:
        for _ in Fm.iter_segments(path, family):
            pass
    assert re.search(rf"{re.escape(str(path))}: record \d+ at byte offset \d+", str(info.value))
    assert str(info.value) == rd.stats.errors[0]


@pytest.mark.parametrize("family", list(Fm.FAMILIES))
def test_reader_fuzz_raises_only_format_errors(tmp_path, family):
    _fuzz(tmp_path, family, 2_800, seed=len(family))


@pytest.mark.slow
@pytest.mark.parametrize("family", list(Fm.FAMILIES))
def test_reader_fuzz_large(tmp_path, family):
    _fuzz(tmp_path, family, 28_000, seed=100 + len(family))
