"""Peak memory of rlu on bombs: conversion of gzip shards that inflate to gigabytes (zeros, one
huge record header, valid windows, valid 100 MiB records), a download whose chunked body never
ends, sampling and validating a dataset with a zlib bomb frame, importing an .npz whose header
claims 1e12 values.

Each command runs as its own process under GNU ``/usr/bin/time -v`` (and ``timeout``, so a
command that would run forever is stopped and its figure is still printed); its "Maximum
resident set size" (the largest of the process and the reader processes it waited for) is
printed with the wall time and the exit code. The endless body comes from a server thread of
this script on 127.0.0.1, which also prints how many bytes it sent before the client hung up.
The bar (issues 15 and 30): under 512 MB.

    PYTHONPATH=. .venv/bin/python bench/hostile_memory.py [--workdir DIR] [--gib 2.5]
        [--only WORD...]
"""

from __future__ import annotations

import argparse
import gzip
import hashlib
import http.server
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import zlib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TASK = "control_suite/cartpole_swingup"


def _members(block: bytes, total: int) -> bytes:
    """A multi-member gzip file whose members all inflate to ``block``, ``total`` bytes in all
    (the reader concatenates members, as gzip does)."""
    member = gzip.compress(block, compresslevel=9, mtime=0)
    return member * max(1, total // len(block))


def zeros_bomb(path: Path, total: int) -> None:
    path.write_bytes(_members(b"\0" * (64 << 20), total))


def record_bomb(path: Path, total: int) -> None:
    """One valid record header declaring 120 MiB (the cap is 128 MiB), then zeros."""
    from rlu.data.release.framing import masked_crc32c

    length = 120 << 20
    header = length.to_bytes(8, "little")
    head = header + masked_crc32c(header).to_bytes(4, "little")
    first = gzip.compress(head + b"\0" * ((64 << 20) - len(head)), 9, mtime=0)
    path.write_bytes(first + _members(b"\0" * (64 << 20), total - (64 << 20)))


def windows_bomb(path: Path, total: int) -> None:
    """Valid control-suite windows, one record repeated: a real conversion of ``total`` bytes."""
    from rlu.data.release import families as Fm
    from rlu.data.release.framing import frame

    rng = np.random.default_rng(0)
    rec = {
        "observation/position": rng.standard_normal((2, 3)).astype(np.float32),
        "observation/velocity": rng.standard_normal((2, 2)).astype(np.float32),
        "action": rng.uniform(-1, 1, (2, 1)).astype(np.float32),
        "reward": np.float32([0.5, 0.5]),
        "discount": np.float32([1, 1]),
        "step_type": np.float32([1, 1]),
    }
    one = frame(Fm.encode_sequence(rec))
    path.write_bytes(_members(one * ((64 << 20) // len(one)), total))


def atari_bomb(path: Path, total: int) -> None:
    """Valid Atari transitions (eight PNG frames each), one record repeated."""
    from rlu.data.release import families as Fm
    from rlu.data.release.framing import frame

    frames = np.zeros((84, 84, 5), np.uint8)
    frames[40:44, 10:70] = 200  # flat screens with a bar, as Atari frames mostly are
    rec = {
        "o_t": frames[..., :4],
        "o_tp1": frames[..., 1:],
        "a_t": 1,
        "a_tp1": 2,
        "r_t": 0.0,
        "d_t": 1.0,
        "episode_id": 7,
        "episode_return": 3.0,
    }
    one = frame(Fm.encode_atari_transition(rec))
    path.write_bytes(_members(one * ((16 << 20) // len(one)), total))


def long_records(path: Path, family: str, n: int = 30, mib: int = 100) -> None:
    """``n`` valid records of ``mib`` MiB each (a few kB of gzip apiece): a real record of the
    family plus a bytes feature no loader names, padded with zeros. 30 of 100 MiB: the 3 MB
    shard of issue 30 that took the old reader to 3.2 GB before its first record was decoded."""
    from rlu.data.release import example as ex
    from rlu.data.release import families as Fm
    from rlu.data.release.framing import frame

    if family == "dm_control_suite":
        payload = Fm.encode_sequence(
            {
                "observation/position": np.zeros((2, 3), np.float32),
                "observation/velocity": np.zeros((2, 2), np.float32),
                "action": np.zeros((2, 1), np.float32),
                "reward": np.float32([0.5, 0.5]),
                "discount": np.float32([1, 1]),
                "step_type": np.float32([1, 1]),
            }
        )
    else:
        t = 5
        payload = Fm.encode_atari_episode(
            {
                "observations": np.zeros((t, 84, 84), np.uint8),
                "actions": np.zeros(t, np.int64),
                "unclipped_rewards": np.zeros(t, np.float32),
                "clipped_rewards": np.zeros(t, np.float32),
                "discounts": np.ones(t, np.float32),
                "checkpoint_idx": np.int64(0),
                "episode_idx": np.int64(0),
                "episode_return": np.float32(0),
                "clipped_episode_return": np.float32(0),
            }
        )
    big = payload + ex.encode_example({"padding": [b"\0" * (mib << 20)]})
    path.write_bytes(gzip.compress(frame(big), 9, mtime=0) * n)


class _Endless(http.server.BaseHTTPRequestHandler):
    """Any GET: a chunked body of zeros that never ends (until the client hangs up)."""

    protocol_version = "HTTP/1.1"

    def log_message(self, *a):  # quiet
        pass

    def do_GET(self):  # noqa: N802
        self.send_response(200)
        self.send_header("Transfer-Encoding", "chunked")
        self.end_headers()
        block = b"\0" * (1 << 20)
        chunk = b"%x\r\n" % len(block) + block + b"\r\n"
        try:
            while True:
                self.wfile.write(chunk)
                self.server.sent += len(block)
        except OSError:  # the client hung up
            pass


def endless_server() -> http.server.ThreadingHTTPServer:
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Endless)
    srv.daemon_threads = True
    srv.sent = 0
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv


def bomb_frame_dataset(dest: Path) -> None:
    """A Pong dataset (zlib frames) whose frame 5 is a stream of frame size inflating to 6 MiB."""
    from rlu.data import Schema
    from rlu.data.synthetic import write_synthetic
    from rlu.tasks import get_task

    schema = Schema.for_task(get_task("atari/Pong"), image_encoding="zlib")
    ds = write_synthetic(dest, schema, 20, 200, seed=0)
    blob = zlib.compress(b"\0" * (6 << 20), 9)
    off = np.fromfile(ds / "steps" / "observation.offsets.bin", "<i8")
    data = (ds / "steps" / "observation.zlib").read_bytes()
    new = data[: off[5]] + blob + data[off[6] :]
    off[6:] += len(blob) - (off[6] - off[5])
    (ds / "steps" / "observation.zlib").write_bytes(new)
    off.tofile(ds / "steps" / "observation.offsets.bin")
    m = json.loads((ds / "manifest.json").read_text())
    for rel in ("steps/observation.zlib", "steps/observation.offsets.bin"):
        raw = (ds / rel).read_bytes()
        m["files"][rel] = {"bytes": len(raw), "sha256": hashlib.sha256(raw).hexdigest()}
    (ds / "manifest.json").write_text(json.dumps(m))


def npz_claiming(path: Path) -> None:
    import io
    import zipfile

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": "<f4", "fortran_order": False, "shape": (10**12,)}
    )
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("rewards.npy", buf.getvalue() + b"\0" * 4096)


ONLY: list[str] = []


def wanted(label: str) -> bool:
    return not ONLY or any(word in label for word in ONLY)


def measure(label: str, argv: list[str], limit: int = 1800) -> None:
    """One row: peak RSS, wall time, exit code (124: stopped by ``timeout`` after ``limit`` s)
    and the first line of its error."""
    if not wanted(label):
        return
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for k in ("http_proxy", "https_proxy", "HTTP_PROXY", "HTTPS_PROXY", "all_proxy", "ALL_PROXY"):
        env.pop(k, None)  # the endless server is on 127.0.0.1
    out = subprocess.run(
        ["/usr/bin/time", "-v", "timeout", str(limit), *argv],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
    )
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", out.stderr).group(1))
    wall = re.search(r"Elapsed \(wall clock\) time.*: (\S+)", out.stderr).group(1)
    last = [ln for ln in out.stderr.splitlines() if ln.startswith("rlu:") or "Error" in ln]
    code = re.search(r"Exit status: (\d+)", out.stderr).group(1)
    print(f"| {label} | {rss / 1024:,.0f} MB | {wall} | {code} | {(last or [''])[0][:90]} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workdir", default=None)
    p.add_argument("--gib", type=float, default=2.5, help="inflated size of the gzip bombs")
    p.add_argument("--only", nargs="*", default=[], help="run the commands whose label has one")
    args = p.parse_args()
    ONLY[:] = args.only
    work = Path(args.workdir or tempfile.mkdtemp(prefix="rlu-bombs-"))
    work.mkdir(parents=True, exist_ok=True)
    total = int(args.gib * (1 << 30))
    py = sys.executable
    rlu = [py, "-m", "rlu"]
    zeros, record, windows = work / "zeros", work / "record", work / "windows"
    zeros_bomb(zeros, total)
    record_bomb(record, total)
    windows_bomb(windows, total)
    atari = work / "run_1-00000-of-00001"
    atari_bomb(atari, total // 5)
    npz_claiming(work / "claims.npz")
    bomb_frame_dataset(work / "pong")
    sizes = {p.name: p.stat().st_size for p in (zeros, record, windows)}
    print(f"gzip bombs inflating to {total / 2**30:.2f} GiB; on disk {sizes}\n")
    print("| command | peak RSS | wall | exit | message |\n|---|---:|---:|---:|---|")
    convert = [*rlu, "convert", "--family", "dm_control_suite", "--task", TASK]
    for name, path, extra in (
        ("zeros", zeros, []),
        ("zeros --skip-corrupt", zeros, ["--skip-corrupt"]),
        ("120 MiB record", record, []),
        ("120 MiB record --skip-corrupt", record, ["--skip-corrupt"]),
    ):
        shutil.rmtree(work / "out", ignore_errors=True)
        measure(f"convert, gzip bomb: {name}", [*convert, "--out", str(work / "out"), *extra,
                                                  str(path)])  # fmt: skip
    for workers in (1, 2):
        shutil.rmtree(work / "out", ignore_errors=True)
        measure(
            f"convert, {args.gib:g} GiB of valid windows, --workers {workers}",
            [*convert, "--out", str(work / "out"), "--workers", str(workers), str(windows)],
        )
    for workers in (1, 2):
        shutil.rmtree(work / "out", ignore_errors=True)
        measure(
            f"convert, {args.gib / 5:g} GiB of valid Atari transitions, --workers {workers}",
            [*rlu, "convert", "--family", "atari", "--task", "atari/Pong", "--out",
             str(work / "out"), "--workers", str(workers), str(atari)],
        )  # fmt: skip
    for family, task in (("dm_control_suite", TASK), ("atari_episodes_ordered", "atari/Pong")):
        label = f"convert, 30 valid 100 MiB {family} records"
        if not wanted(label):
            continue
        shard = work / family / "run_1-00000-of-00001"
        shard.parent.mkdir(exist_ok=True)
        long_records(shard, family)
        shutil.rmtree(work / "out", ignore_errors=True)
        label += f" ({shard.stat().st_size / 1e6:.1f} MB of gzip)"
        measure(label, [*rlu, "convert", "--family", family, "--task", task, "--out",
                        str(work / "out"), "--quiet", str(shard)])  # fmt: skip
    if wanted("download, an endless chunked body"):
        srv = endless_server()
        measure(
            "download, an endless chunked body",
            [*rlu, "download", TASK, "--shards", "0", "--retries", "0", "--quiet", "--base-url",
             f"http://127.0.0.1:{srv.server_address[1]}", "--cache-dir", str(work / "cache")],
            limit=60,
        )  # fmt: skip
        left = sum(p.stat().st_size for p in (work / "cache").rglob("*") if p.is_file())
        print(f"(the server sent {srv.sent / 2**20:,.0f} MiB before the client hung up; "
              f"{left / 2**20:,.1f} MiB left in the cache)")  # fmt: skip
        srv.shutdown()
    shutil.rmtree(work / "out", ignore_errors=True)
    sample = (
        "import sys; from rlu.data import open_dataset; from rlu.data.views import make_sampler\n"
        "from rlu.types import BatchSpec\n"
        "s = make_sampler(open_dataset(sys.argv[1]), BatchSpec(256), seed=0)\n"
        "for _ in range(200): s.sample()\n"
    )
    measure("sample a dataset with a bomb frame", [py, "-c", sample, str(work / "pong")])
    measure("validate a dataset with a bomb frame", [*rlu, "validate", str(work / "pong")])
    measure(
        "import an .npz whose header claims 1e12 values",
        [*rlu, "import", str(work / "claims.npz"), "--format", "d4rl", "--task", TASK,
         "--out", str(work / "imported")],
    )  # fmt: skip
    if args.workdir is None:
        shutil.rmtree(work)


if __name__ == "__main__":
    main()
