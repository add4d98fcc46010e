"""TFRecord framing: CRCs, gzip sniffing, streaming across chunks, damage, fuzzing."""

from __future__ import annotations

import gzip
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rlu.data.release import framing as F
from rlu.types import FormatError


def test_crc32c_test_vector():
    assert F.crc32c(b"123456789") == 0xE3069283
    assert F.masked_crc32c(b"123456789") == 0xC78AB0E5


def _payloads(n=50, seed=0):
    import random

    r = random.Random(seed)
    out = []
    for i in range(n):
        size = 37 if i % 3 else r.randrange(0, 300)  # runs of equal lengths and odd ones
        out.append(bytes(r.randrange(256) for _ in range(size)))
    return out


@pytest.mark.parametrize("compression", ["gzip", None])
def test_round_trip_and_sniffing(tmp_path, compression):
    payloads = _payloads()
    path = tmp_path / "shard"
    F.write_records(path, payloads, compression=compression)
    assert F.is_gzip(path) == (compression == "gzip")
    r = F.RecordReader(path)
    assert list(r) == payloads
    assert r.stats.records == len(payloads) and r.stats.skipped == 0
    assert r.stats.compressed == (compression == "gzip")


def test_records_straddle_chunk_boundaries(tmp_path, monkeypatch):
    monkeypatch.setattr(F, "CHUNK", 7)  # every record and header crosses reads
    payloads = _payloads(40, seed=1) + [b"x" * 5000]
    for comp in ("gzip", None):
        path = tmp_path / f"s{comp}"
        F.write_records(path, payloads, compression=comp)
        assert list(F.read_records(path)) == payloads


def test_concatenated_gzip_members(tmp_path):
    a, b = _payloads(5, 2), _payloads(6, 3)
    data = gzip.compress(b"".join(F.frame(p) for p in a)) + gzip.compress(
        b"".join(F.frame(p) for p in b)
    )
    path = tmp_path / "two_members"
    path.write_bytes(data)
    assert list(F.read_records(path)) == a + b


def test_writer_leaves_no_final_name_on_failure(tmp_path):
    path = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with F.RecordWriter(path) as w:
            w.write(b"abc")
            raise RuntimeError("boom")
    assert not path.exists() and not list(tmp_path.iterdir())


def _plain(tmp_path, payloads):
    data = bytearray(b"".join(F.frame(p) for p in payloads))
    return data


def _offsets(payloads):
    offs, o = [], 0
    for p in payloads:
        offs.append(o)
        o += len(p) + 16
    return offs


def test_payload_crc_mismatch_names_file_and_offset(tmp_path):
    payloads = [b"a" * 10, b"b" * 20, b"c" * 30]
    data = _plain(tmp_path, payloads)
    off = _offsets(payloads)[1]
    data[off + 12 + 3] ^= 0xFF
    path = tmp_path / "bad"
    path.write_bytes(bytes(data))
    with pytest.raises(F.RecordError) as e:
        list(F.read_records(path))
    assert str(path) in str(e.value) and f"byte offset {off}" in str(e.value)
    assert "payload CRC mismatch" in str(e.value)
    assert isinstance(e.value, FormatError)
    # opt-in: skip the bad record, report one skipped
    r = F.RecordReader(path, on_error="skip")
    assert list(r) == [payloads[0], payloads[2]]
    assert r.stats.skipped == 1
    # and with verification off the damaged payload comes through
    assert len(list(F.read_records(path, verify=False))) == 3


def test_length_crc_mismatch_resyncs_in_skip_mode(tmp_path):
    payloads = [b"a" * 10, b"b" * 20, b"c" * 30, b"d" * 5]
    data = _plain(tmp_path, payloads)
    off = _offsets(payloads)[1]
    data[off] ^= 0x01  # the length itself
    path = tmp_path / "bad_len"
    path.write_bytes(bytes(data))
    with pytest.raises(F.RecordError, match=f"length CRC mismatch.*byte offset {off}"):
        list(F.read_records(path))
    r = F.RecordReader(path, on_error="skip")
    assert list(r) == [payloads[0], payloads[2], payloads[3]]
    assert r.stats.skipped == 1


def test_truncated_record(tmp_path):
    payloads = [b"a" * 10, b"b" * 200]
    data = _plain(tmp_path, payloads)[:-50]
    path = tmp_path / "trunc"
    path.write_bytes(bytes(data))
    off = _offsets(payloads)[1]
    with pytest.raises(F.RecordError, match=f"truncated record.*byte offset {off}"):
        list(F.read_records(path))
    r = F.RecordReader(path, on_error="skip")
    assert list(r) == [payloads[0]] and r.stats.skipped == 1
    gz = tmp_path / "trunc.gz"
    gz.write_bytes(gzip.compress(bytes(data)))
    with pytest.raises(F.RecordError, match=f"byte offset {off}"):
        list(F.read_records(gz))


def test_cut_gzip_stream(tmp_path):
    payloads = _payloads(200, seed=4)
    path = tmp_path / "full"
    F.write_records(path, payloads)
    data = path.read_bytes()
    cut = tmp_path / "cut"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(F.RecordError) as e:
        list(F.read_records(cut))
    msg = str(e.value)
    assert str(cut) in msg and "gzip stream cut" in msg and "byte offset" in msg
    # the offset is where the first incomplete record starts
    assert e.value.offset in _offsets(payloads)
    r = F.RecordReader(cut, on_error="skip")
    got = list(r)
    assert got == payloads[: len(got)] and 0 < len(got) < len(payloads)
    assert r.stats.skipped == 1 and any("gzip stream cut" in m for m in r.stats.errors)


def test_corrupt_gzip_stream(tmp_path):
    path = tmp_path / "full"
    F.write_records(path, _payloads(100, seed=5))
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match=str(path)):
        list(F.read_records(path))


def _only_format_errors(path):
    for mode in ("raise", "skip"):
        try:
            for _ in F.RecordReader(path, on_error=mode):
                pass
        except FormatError:
            pass


@settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.binary(max_size=400))
def test_fuzz_random_bytes(tmp_path, data):
    path = tmp_path / "fuzz"
    path.write_bytes(data)
    _only_format_errors(path)
    path.write_bytes(b"\x1f\x8b" + data)
    _only_format_errors(path)


@settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    flips=st.lists(st.tuples(st.integers(0, 10_000), st.integers(1, 255)), min_size=1, max_size=4),
    cut=st.integers(0, 10_000),
    gz=st.booleans(),
)
def test_fuzz_mutated_files(tmp_path, flips, cut, gz):
    raw = b"".join(F.frame(p) for p in _payloads(20, seed=6))
    data = bytearray(gzip.compress(raw) if gz else raw)
    for pos, x in flips:
        data[pos % len(data)] ^= x
    path = tmp_path / "mut"
    path.write_bytes(bytes(data[: max(1, cut % (len(data) + 1))]))
    _only_format_errors(path)


def test_header_helpers():
    rec = F.frame(b"hello")
    (n,) = struct.unpack("<Q", rec[:8])
    assert n == 5 and struct.unpack("<I", rec[8:12])[0] == F.masked_crc32c(rec[:8])


@pytest.mark.parametrize("n", [60, 100])  # 100: one CRC call over the block first
def test_crc_mismatch_inside_a_run_of_equal_lengths(tmp_path, n):
    assert 60 < F._BLOCK_CRC_RUN <= 100
    payloads = [bytes([i]) * 40 for i in range(n)]  # the vectorised path frames these
    data = bytearray(b"".join(F.frame(p) for p in payloads))
    off = 33 * (40 + 16)
    data[off + 12 + 5] ^= 0x10
    path = tmp_path / "run"
    path.write_bytes(gzip.compress(bytes(data)))
    with pytest.raises(F.RecordError, match=f"payload CRC mismatch at byte offset {off};"):
        list(F.read_records(path))
    r = F.RecordReader(path, on_error="skip")
    assert list(r) == payloads[:33] + payloads[34:] and r.stats.skipped == 1


def _reference(stream: bytes, plain: bool) -> tuple[list[bytes], list[int], list[int]]:
    """Record by record, the framing rules written plainly: (payloads, their offsets, the offsets
    of the damage skipped). A bad header resynchronises on the next offset holding a length
    within the limit, a non-zero CRC and that CRC; a record past the end of a plain file is a bad
    header; at the end of a gzip stream it is a truncated record, and reading stops."""
    out, at, bad = [], [], []
    pos, n = 0, len(stream)

    def header_ok(o: int) -> bool:
        (length,) = struct.unpack_from("<Q", stream, o)
        crc = stream[o + 8 : o + 12]
        return (
            length <= F.MAX_RECORD_BYTES
            and crc != b"\0\0\0\0"
            and crc == struct.pack("<I", F.masked_crc32c(stream[o : o + 8]))
        )

    skipping = False
    while pos < n:
        if skipping:
            while pos <= n - 12 and not header_ok(pos):
                pos += 1
            if pos > n - 12:
                return out, at, bad
            skipping = False
        if n - pos < 12:
            bad.append(pos)
            return out, at, bad
        (length,) = struct.unpack_from("<Q", stream, pos)
        crc = stream[pos + 8 : pos + 12]
        if crc != struct.pack("<I", F.masked_crc32c(stream[pos : pos + 8])) or (
            length > F.MAX_RECORD_BYTES or (plain and pos + length + 16 > n)
        ):
            bad.append(pos)
            skipping, pos = True, pos + 1
            continue
        if pos + length + 16 > n:
            bad.append(pos)
            return out, at, bad
        payload = stream[pos + 12 : pos + 12 + length]
        if stream[pos + 12 + length : pos + 16 + length] == struct.pack(
            "<I", F.masked_crc32c(payload)
        ):
            out.append(payload)
            at.append(pos)
        else:
            bad.append(pos)
        pos += length + 16
    return out, at, bad


@pytest.mark.parametrize("chunk", [7, 61, 500, 1 << 22])
def test_damage_read_as_the_plain_rules_read_it(tmp_path, monkeypatch, chunk):
    """The framer (chunks framed in place, a straddling record joined with the next chunk's
    start, runs of equal headers taken as blocks) against the rules written record by record:
    the same payloads, offsets and skipped damage in every chunking, and in the default mode
    the error at the first damage."""
    import random

    monkeypatch.setattr(F, "CHUNK", chunk)
    r = random.Random(chunk)
    # runs of 70 equal lengths: a block CRC over 64 or more of them, as well as shorter runs
    payloads = [bytes([i % 256]) * (40 if i % 100 < 70 else r.randrange(300)) for i in range(250)]
    clean = b"".join(F.frame(p) for p in payloads)
    for trial in range(12):
        data = bytearray(clean)
        for _ in range(1 + trial % 3):
            data[r.randrange(len(data))] ^= 1 << r.randrange(8)
        if trial % 4 == 3:
            del data[r.randrange(len(data) // 2, len(data)) :]
        stream = bytes(data)
        for gz in (False, True):
            path = tmp_path / f"d{trial}{gz}"
            path.write_bytes(gzip.compress(stream) if gz else stream)
            want, want_at, want_bad = _reference(stream, plain=not gz)
            rd = F.RecordReader(path, on_error="skip")
            got, got_at = [], []
            for batch, offsets in rd.batches_with_offsets():
                got.extend(batch)
                got_at.extend(offsets)
                assert all(type(p) is bytes for p in batch)
            assert got == want and got_at == want_at, (trial, gz)
            assert rd.stats.skipped == len(want_bad), (trial, gz, rd.stats.errors)
            assert rd.stats.records == len(want)
            if want_bad:
                with pytest.raises(F.RecordError) as e:
                    list(F.RecordReader(path))
                assert e.value.offset == want_bad[0] and e.value.path == str(path)
            else:
                assert list(F.RecordReader(path)) == want
