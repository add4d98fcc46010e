"""tf.train.Example codec: round trips, packed and unpacked lists, batch decoding, fuzzing."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rlu.codecs import example as E
from rlu.types import FormatError


def _same(a, b):
    if isinstance(a, list):
        return a == b
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


FEATURES = {
    "f": np.array([1.5, -0.0, np.inf, 3.25e-39], np.float32),  # negative zero, inf, subnormal
    "i": np.array([0, 1, -1, 2**63 - 1, -(2**63), 300, 127, 128], np.int64),
    "b": [b"", b"\x00\xff", b"x" * 300],
    "empty_f": np.zeros(0, np.float32),
    "key/with:odd chars é": np.array([7], np.int64),
}


@pytest.mark.parametrize("packed", [True, False])
def test_round_trip(packed):
    payload = E.encode_example(FEATURES, packed=packed)
    got = E.decode_example(payload)
    assert set(got) == set(FEATURES)
    for k, v in FEATURES.items():
        assert _same(got[k], v), k


def test_nan_bits_survive():
    nan = np.array([0x7FC00001, 0xFFC00000], np.uint32).view(np.float32)
    got = E.decode_example(E.encode_example({"x": nan}))["x"]
    assert got.view(np.uint32).tolist() == [0x7FC00001, 0xFFC00000]


def test_uint64_reinterpreted():
    ids = np.array([0, 2**63, 2**64 - 1], np.uint64)
    got = E.decode_example(E.encode_example({"id": ids}))["id"]
    assert got.view(np.uint64).tolist() == ids.tolist()


def test_varints_match_protobuf_rules():
    vals = np.array([0, 1, 127, 128, 16383, 16384, -1, -(2**63), 2**62], np.int64)
    enc = E.encode_varints(vals)
    # -1 and INT64_MIN take 10 bytes, as protobuf writes negative int64
    assert E.encode_varints(np.array([-1])) == b"\xff" * 9 + b"\x01"
    assert E.decode_varints(enc).tolist() == vals.tolist()
    with pytest.raises(FormatError):
        E.decode_varints(b"\x80\x80")  # truncated
    with pytest.raises(FormatError):
        E.decode_varints(b"\xff" * 11 + b"\x01")  # longer than 10 bytes


def test_repeated_key_and_unknown_fields():
    a = E.encode_example({"k": np.array([1.0], np.float32)})
    b = E.encode_example({"k": np.array([2, 3], np.int64)})
    # two Features fields in one Example merge; the later map entry of a key wins
    unknown = b"\x10\x05" + b"\x1a\x02ab"  # field 2 varint, field 3 bytes: skipped
    got = E.decode_example(a + unknown + b)
    assert got["k"].tolist() == [2, 3] and got["k"].dtype == np.int64


def _random_records(rng, n, int_wide=False):
    recs = []
    for _ in range(n):
        ints = rng.integers(0, 100, 3)
        if int_wide:
            ints = rng.integers(-(2**40), 2**40, 3)
        recs.append(
            E.encode_example(
                {
                    "obs": rng.standard_normal(6).astype(np.float32),
                    "a": ints.astype(np.int64),
                    "cam": [rng.integers(0, 256, 24, dtype=np.uint8).tobytes()],
                }
            )
        )
    return recs


@pytest.mark.parametrize("int_wide", [False, True])
def test_decode_batch_equals_record_by_record(int_wide):
    rng = np.random.default_rng(0)
    recs = _random_records(rng, 64, int_wide)
    cols = E.decode_batch(recs)
    ref = E.stack_examples([E.decode_example(r) for r in recs])
    assert set(cols) == set(ref)
    for k in ref:
        if isinstance(ref[k], E.BytesColumn):
            assert cols[k].values == ref[k].values
            assert np.array_equal(cols[k].concatenated(), ref[k].concatenated())
        elif ref[k].dtype == object:
            assert all(_same(x, y) for x, y in zip(cols[k], ref[k], strict=True))
        else:
            assert _same(cols[k], ref[k]), k


def test_decode_batch_template_path_is_taken():
    rng = np.random.default_rng(1)
    recs = _random_records(rng, 32)
    layout = E._layout(recs[0])
    cols, ok = E._template_decode(recs, layout)
    assert ok.all()  # same lengths and structure: no record falls back
    assert cols["obs"].shape == (32, 6) and cols["cam"].flat.shape == (32, 24)


def test_decode_batch_missing_keys_read_empty():
    recs = [E.encode_example({"a": np.ones(2, np.float32)}), E.encode_example({"b": [b"x"]})]
    cols = E.decode_batch(recs)
    assert cols["a"][1].size == 0 and cols["b"].values == [[], [b"x"]]


def _only_format_errors(data: bytes):
    try:
        E.decode_example(data)
    except FormatError:
        pass
    try:
        E.decode_batch([data] * 9)
    except FormatError:
        pass


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=300))
def test_fuzz_random_bytes(data):
    _only_format_errors(data)


@settings(max_examples=500, deadline=None)
@given(
    flips=st.lists(st.tuples(st.integers(0, 10_000), st.integers(1, 255)), min_size=1, max_size=3),
    cut=st.integers(0, 10_000),
)
def test_fuzz_mutated_examples(flips, cut):
    data = bytearray(E.encode_example(FEATURES))
    for pos, x in flips:
        data[pos % len(data)] ^= x
    _only_format_errors(bytes(data[: cut % (len(data) + 1)]))
    # the batch path with one mutated record among valid ones of the same length
    good = E.encode_example(FEATURES)
    if len(data) == len(good):
        try:
            E.decode_batch([good] * 8 + [bytes(data)])
        except FormatError:
            pass
