"""Hostile caches, servers and shards for ``rlu download``, ``rlu convert`` and
``rlu.load_dataset(..., source="release")``: every case fails on the code before the fix.

- Files outside are never written or read through a link planted in the cache: the ``.part`` of
  a shard, its ``.part.json`` note, the entry's lock, the manifest and its lock, the dataset lock
  of ``load_dataset`` (a symbolic link, or a hard link to a victim file).
- Bodies are bounded: an endless chunked body stops at the family's largest shard size, a
  ``Content-Length`` beyond it is refused before a byte is read.
- Records are bounded and decoded as they stream: a 1.2 MB gzip shard of twelve valid 100 MiB
  records is refused at its first header (under a 1 GiB address-space limit; the old reader
  buffered them all and died of MemoryError), long records of an episode family are decoded one
  by one, and an Atari episode longer than the recording allows is refused before its frames are
  decoded.

Servers run on 127.0.0.1 only.
"""

from __future__ import annotations

import gzip
import http.server
import os
import resource
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.servers import direct, serve

pytest.importorskip("google_crc32c", reason="the release extra (google-crc32c) is not installed")

from rlu.cli import main  # noqa: E402
from rlu.codecs import example as ex  # noqa: E402
from rlu.data.release import families as Fm  # noqa: E402
from rlu.data.release.framing import RecordReader, frame  # noqa: E402
from rlu.domains import records  # noqa: E402
from rlu.domains.atari import release as atari_release  # noqa: E402
from rlu.types import FormatError, RluError  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
TASK = "control_suite/cartpole_swingup"
OBJ = "dm_control_suite/cartpole_swingup/train-00000-of-00100"
BOUND = 256 << 20  # the largest dm_control_suite shard rlu accepts (Family.max_shard_bytes)
VICTIM = b"a file outside the cache that nobody may touch\n"


def _window() -> dict[str, np.ndarray]:
    return {
        "observation/position": np.zeros((2, 3), np.float32),
        "observation/velocity": np.zeros((2, 2), np.float32),
        "action": np.zeros((2, 1), np.float32),
        "reward": np.float32([0.5, 0.5]),
        "discount": np.float32([1, 1]),
        "step_type": np.float32([1, 1]),
    }


def _shard_bytes() -> bytes:
    return gzip.compress(
        b"".join(frame(records.encode_sequence(_window())) for _ in range(8)), mtime=0
    )


class _Handler(http.server.BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"

    def log_message(self, *a):  # quiet
        pass

    def do_GET(self):  # noqa: N802
        srv = self.server
        srv.requests += 1
        if srv.mode == "endless":  # chunked zeros, up to a cap far past the bound
            self.send_response(200)
            self.send_header("Transfer-Encoding", "chunked")
            self.end_headers()
            block = b"\0" * (1 << 20)
            chunk = b"%x\r\n" % len(block) + block + b"\r\n"
            try:
                while srv.sent < srv.cap:
                    self.wfile.write(chunk)
                    srv.sent += len(block)
                self.wfile.write(b"0\r\n\r\n")
            except OSError:  # the client hung up: what it should do
                pass
            self.close_connection = True
            return
        if srv.mode == "huge-length":
            self.send_response(200)
            self.send_header("Content-Length", str(10 << 30))
            self.end_headers()
            self.wfile.write(b"\0" * 4096)
            self.close_connection = True
            return
        body = srv.body
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)


@pytest.fixture
def server(monkeypatch):
    direct(monkeypatch)
    with serve(_Handler, daemon_threads=True, mode="ok", body=_shard_bytes(), requests=0, sent=0,
               cap=0) as srv:  # fmt: skip
        yield srv


def _download(srv, cache: Path, capsys, *extra: str) -> tuple[int, list[str]]:
    argv = ["download", TASK, "--shards", "0", "--base-url", srv.url, "--cache-dir", str(cache)]
    code = main([*argv, *extra])  # stderr is no terminal: progress lines only after 10 s
    return code, capsys.readouterr().err.strip().splitlines()


# --- links planted in the cache ----------------------------------------------------------------
def _entry(cache: Path) -> Path:
    return cache / "release" / OBJ


PLANTS = {
    "part-symlink": lambda c: (_entry(c).parent / (_entry(c).name + ".part"), "symlink"),
    "part-hardlink": lambda c: (_entry(c).parent / (_entry(c).name + ".part"), "hardlink"),
    "part-note-symlink": lambda c: (_entry(c).parent / (_entry(c).name + ".part.json"), "symlink"),
    "entry-lock-symlink": lambda c: (_entry(c).parent / f".{_entry(c).name}.lock", "symlink"),
    "entry-lock-hardlink": lambda c: (_entry(c).parent / f".{_entry(c).name}.lock", "hardlink"),
    "manifest-symlink": lambda c: (c / "release" / "manifest.json", "symlink"),
    "manifest-lock-symlink": lambda c: (c / "release" / "manifest.json.lock", "symlink"),
    "entry-symlink": lambda c: (_entry(c), "symlink"),
}


@pytest.mark.parametrize("name", sorted(PLANTS))
def test_a_link_planted_in_the_cache_is_refused(name, tmp_path, server, capsys):
    victim = tmp_path / "outside" / "victim"
    victim.parent.mkdir()
    victim.write_bytes(VICTIM)
    cache = tmp_path / "cache"
    where, kind = PLANTS[name](cache)
    where.parent.mkdir(parents=True, exist_ok=True)
    if kind == "symlink":
        where.symlink_to(victim)
    else:
        os.link(victim, where)
    if name == "entry-symlink":  # a manifest entry that the planted link matches: "reusable"
        import hashlib
        import json

        sha = hashlib.sha256(VICTIM).hexdigest()
        (cache / "release" / "manifest.json").write_text(
            json.dumps({OBJ: {"size": len(VICTIM), "sha256": sha}})
        )
    code, lines = _download(server, cache, capsys)
    # refused, naming the link: before, the victim was written through (truncated, given the
    # shard, its note or a PID), or read as the manifest or as a reusable shard
    assert code == 2 and len(lines) == 1, lines
    assert "link" in lines[0] and str(where) in lines[0] and "Traceback" not in lines[0]
    assert victim.read_bytes() == VICTIM


def test_a_linked_dataset_lock_of_load_dataset_is_refused(tmp_path, server):
    import rlu
    from rlu.data.release import catalog
    from rlu.data.release.load import release_dataset_path

    victim = tmp_path / "victim"
    victim.write_bytes(VICTIM)
    cache = tmp_path / "cache"
    dest = release_dataset_path(catalog.select(TASK, shards="0"), cache, all_shards=False)
    os.makedirs(os.path.dirname(dest))
    os.symlink(victim, dest + ".lock")
    kw = dict(source="release", cache_dir=cache, base_url=server.url, shards="0", progress=False)
    with pytest.raises(RluError, match="symbolic link"):
        rlu.load_dataset(TASK, **kw)
    assert victim.read_bytes() == VICTIM


@pytest.mark.parametrize("kind", ["symlink", "hardlink"])
def test_a_linked_lock_of_a_convert_output_is_refused(tmp_path, capsys, kind):
    """The same lock guards every output (``rlu train --out`` wrote its PID into the victim)."""
    victim = tmp_path / "victim"
    victim.write_bytes(VICTIM)
    shard = tmp_path / "train-00000-of-00001"
    shard.write_bytes(_shard_bytes())
    lock = tmp_path / ".out.lock"
    os.symlink(victim, lock) if kind == "symlink" else os.link(victim, lock)
    argv = ["convert", "--family", "dm_control_suite", "--task", TASK, "--out"]
    code = main([*argv, str(tmp_path / "out"), str(shard)])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and str(lock) in lines[0] and "link" in lines[0], lines
    assert victim.read_bytes() == VICTIM and not (tmp_path / "out").exists()


# --- bodies without end --------------------------------------------------------------------
def test_an_endless_chunked_body_stops_at_the_bound(tmp_path, server, capsys):
    server.mode, server.cap = "endless", BOUND + (256 << 20)
    code, lines = _download(server, tmp_path, capsys, "--retries", "0")
    assert code == 2 and len(lines) == 1, lines
    assert f"goes on past {BOUND:,} bytes without a length" in lines[0]
    assert server.sent < server.cap  # the client hung up at the bound
    assert server.requests == 1  # permanent: not tried again
    assert not list(tmp_path.rglob("*.part")) and not _entry(tmp_path).exists()
    assert Fm.FAMILIES["dm_control_suite"].max_shard_bytes == BOUND


def test_a_content_length_past_the_bound_is_refused_unread(tmp_path, server, capsys):
    server.mode = "huge-length"
    code, lines = _download(server, tmp_path, capsys, "--retries", "0")
    assert code == 2 and len(lines) == 1, lines
    assert f"announces {10 << 30:,} bytes, more than any shard of this family" in lines[0]
    assert not list(tmp_path.rglob("*.part"))


# --- records past every bound ----------------------------------------------------------------
def _long_record_shard(path: Path, payload: bytes, n: int, mib: int) -> int:
    """``n`` copies of ``payload`` grown to ``mib`` MiB by a bytes feature no loader names (the
    record stays valid), as one gzip member each: a few kB on disk per 100 MiB."""
    big = payload + ex.encode_example({"padding": [b"\0" * (mib << 20)]})
    one = gzip.compress(frame(big), 9, mtime=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(one * n)
    return len(big) + 16


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))


def test_a_shard_of_100_mib_records_is_refused_in_bounded_memory(tmp_path):
    shard = tmp_path / "train-00000-of-00001"
    _long_record_shard(shard, records.encode_sequence(_window()), 12, 100)
    assert shard.stat().st_size < 2 << 20  # 1.2 GB of records in a little over 1 MB
    argv = ["convert", "--family", "dm_control_suite", "--task", TASK, "--out",
            str(tmp_path / "out"), str(shard)]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, "-m", "rlu", *argv],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        preexec_fn=_limit_memory,  # 1 GiB of address space: the old reader's MemoryError
        timeout=600,
    )
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1, out.stderr[-2000:]
    assert "record length 104,857," in lines[0] and "is over the limit of 4,194,304" in lines[0]
    assert not (tmp_path / "out").exists()


def test_long_records_of_an_episode_family_are_decoded_as_they_stream(tmp_path):
    from tests.release.test_families import atari_episode

    shard = tmp_path / "run_1-00000-of-00001"
    ep = atari_release.encode_atari_episode(atari_episode(np.random.default_rng(0), 5))
    stride = _long_record_shard(shard, ep, 3, 70)  # each past the decode batch's byte bound
    reader = RecordReader(shard)
    segments = Fm.iter_segments(shard, "atari_episodes_ordered", reader=reader)
    first = next(segments)
    assert len(first) == 1 and reader.stats.bytes_read == stride  # the second is not read yet
    assert sum(len(b) for b in segments) == 2 and reader.stats.bytes_read == 3 * stride


def test_an_atari_episode_past_the_recording_limit_is_refused_undecoded(tmp_path):
    from rlu.codecs.png import encode_png

    t = 30_000
    frame_png = encode_png(np.zeros((84, 84), np.uint8))
    r = np.zeros(t, np.float32)
    feats = {
        "observations": [frame_png] * t,  # 30,000 tiny PNGs: 210 MB once decoded
        "actions": np.zeros(t, np.int64),
        "unclipped_rewards": r,
        "clipped_rewards": r,
        "discounts": np.ones(t, np.float32),
        "checkpoint_idx": np.asarray([0], np.int64),
        "episode_idx": np.asarray([0], np.int64),
        "episode_return": np.asarray([0], np.float32),
        "clipped_episode_return": np.asarray([0], np.float32),
    }
    shard = tmp_path / "run_1-00000-of-00001"
    with Fm.RecordWriter(shard, "gzip") as w:
        w.write(ex.encode_example(feats))
    with pytest.raises(FormatError, match="an episode of 30,000 steps; the recording stopped"):
        list(Fm.iter_segments(shard, "atari_episodes_ordered"))


def test_a_refused_port_is_not_a_hostile_case_but_must_be_quick(tmp_path, capsys):
    """Offline is the commonest bad input of all: one line, no retries (see tests/release)."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    url = f"http://127.0.0.1:{sock.getsockname()[1]}"
    sock.close()
    argv = ["download", TASK, "--shards", "0-7", "--base-url", url, "--cache-dir", str(tmp_path)]
    code = main(argv)
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "connection refused" in lines[0]
