"""Peak memory of rlu on bombs: conversion of gzip shards that inflate to gigabytes (zeros, one
huge record header, valid windows, valid 100 MiB records), a download whose chunked body never
ends, sampling and validating a dataset with a zlib bomb frame, importing an .npz whose header
claims 1e12 values; and (issue 30) importing HDF5 files with gzip datasets and .npz archives with
deflated members that inflate to gigabytes (one array, or every array of consistent shape), and
loading and validating kept behaviour policies whose .npz claims 1e12 values or inflates to
gigabytes; and (issue 39) importing Minari datasets whose gzip arrays inflate to gigabytes (one
array, a whole episode, an infos array), an export's sidecar whose segment table does, and
exporting a large dataset (4.8M steps) to every format, beside a baseline tree's exports.

Each command runs as its own process under GNU ``/usr/bin/time -v`` (and ``timeout``, so a
command that would run forever is stopped and its figure is still printed); its "Maximum
resident set size" (the largest of the process and the reader processes it waited for) is
printed with the wall time and the exit code. The endless body comes from a server thread of
this script on 127.0.0.1, which also prints how many bytes it sent before the client hung up.
The bar (issues 15 and 30): under 512 MB.

    PYTHONPATH=. .venv/bin/python bench/hostile_memory.py [--workdir DIR] [--gib 2.5]
        [--only WORD...] [--interop-only] [--steps 4800000] [--baseline OTHER_RLU_TREE]
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
    from rlu.data.release.framing import frame
    from rlu.domains import records

    rng = np.random.default_rng(0)
    rec = {
        "observation/position": rng.standard_normal((2, 3)).astype(np.float32),
        "observation/velocity": rng.standard_normal((2, 2)).astype(np.float32),
        "action": rng.uniform(-1, 1, (2, 1)).astype(np.float32),
        "reward": np.float32([0.5, 0.5]),
        "discount": np.float32([1, 1]),
        "step_type": np.float32([1, 1]),
    }
    one = frame(records.encode_sequence(rec))
    path.write_bytes(_members(one * ((64 << 20) // len(one)), total))


def atari_bomb(path: Path, total: int) -> None:
    """Valid Atari transitions (eight PNG frames each), one record repeated."""
    from rlu.data.release.framing import frame
    from rlu.domains.atari import release as atari_release

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
    one = frame(atari_release.encode_atari_transition(rec))
    path.write_bytes(_members(one * ((16 << 20) // len(one)), total))


def long_records(path: Path, family: str, n: int = 30, mib: int = 100) -> None:
    """``n`` valid records of ``mib`` MiB each (a few kB of gzip apiece): a real record of the
    family plus a bytes feature no loader names, padded with zeros. 30 of 100 MiB: the 3 MB
    shard of issue 30 that took the old reader to 3.2 GB before its first record was decoded."""
    from rlu.codecs import example as ex
    from rlu.data.release.framing import frame
    from rlu.domains import records
    from rlu.domains.atari import release as atari_release

    if family == "dm_control_suite":
        payload = records.encode_sequence(
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
        payload = atari_release.encode_atari_episode(
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
    shutil.rmtree(dest, ignore_errors=True)  # a --workdir used before
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


def _gzip_zeros(f, name: str, shape: tuple, chunk_rows: int, dtype: str = "f4") -> None:
    """An HDF5 gzip dataset of zeros, every chunk the same compressed chunk (a bomb: 256 KiB or
    more of values in a few hundred stored bytes)."""
    chunks = (chunk_rows, *shape[1:])
    ds = f.create_dataset(name, shape=shape, dtype=dtype, chunks=chunks, compression="gzip")
    blob = zlib.compress(bytes(int(np.prod(chunks)) * np.dtype(dtype).itemsize), 9)
    for i in range(0, shape[0] - chunk_rows + 1, chunk_rows):
        ds.id.write_direct_chunk((i, *([0] * (len(shape) - 1))), blob)


D4RL_COLUMNS = (("observations", (5,)), ("next_observations", (5,)), ("actions", (1,)),
                ("rewards", ()), ("terminals", ()), ("timeouts", ()))  # fmt: skip
"""A cartpole_swingup D4RL file's step arrays (56 bytes a row as float32)."""


def hdf5_one_array_bomb(path: Path, total: int) -> None:
    """A valid 18-row D4RL file whose ``rewards`` declares ``total`` bytes of gzip zeros."""
    import h5py

    from rlu.data import Schema, open_dataset
    from rlu.data.d4rl import to_d4rl
    from rlu.data.synthetic import write_synthetic
    from rlu.tasks import get_task

    src = path.parent / "bomb_src"
    shutil.rmtree(src, ignore_errors=True)
    d = to_d4rl(open_dataset(write_synthetic(src, Schema.for_task(get_task(TASK)), 3, 7, seed=1)))
    with h5py.File(path, "w") as f:
        for k, v in d.items():
            if k != "rewards":
                f.create_dataset(k, data=v)
        _gzip_zeros(f, "rewards", (total // 4,), 1 << 18)


def hdf5_consistent_bomb(path: Path, total: int, episode: int | None = None) -> None:
    """Every step array of a D4RL file declaring the same rows of gzip zeros, ``total`` bytes in
    all; with ``episode``, a terminal every ``episode`` rows (a valid dataset of zeros)."""
    import h5py

    n = total // 56 // (1 << 14) * (1 << 14)
    with h5py.File(path, "w") as f:
        for name, row in D4RL_COLUMNS:
            if name == "terminals" and episode:
                ends = np.zeros(n, np.float32)
                ends[episode - 1 :: episode] = 1
                f.create_dataset(name, data=ends, chunks=(1 << 16,), compression="gzip")
                continue
            _gzip_zeros(f, name, (n, *row), 1 << 14)


def npz_consistent_bomb(path: Path, total: int) -> None:
    """Every step array of a D4RL .npz as a deflated member of zeros, ``total`` bytes in all."""
    import io
    import zipfile

    n = total // 56
    zeros = bytes(16 << 20)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as z:
        for name, row in D4RL_COLUMNS:
            head = io.BytesIO()
            np.lib.format.write_array_header_1_0(
                head, {"descr": "<f4", "fortran_order": False, "shape": (n, *row)}
            )
            with z.open(f"{name}.npy", "w", force_zip64=True) as fh:
                fh.write(head.getvalue())
                left = n * int(np.prod(row)) * 4
                while left:
                    fh.write(zeros[: min(left, len(zeros))])
                    left -= min(left, len(zeros))


def d3rlpy_bomb(path: Path, total: int, consistent: bool) -> None:
    """A one-episode d3rlpy dump whose ``rewards_0`` (or, ``consistent``, every array of the
    episode) declares gzip zeros, ``total`` bytes in all."""
    import h5py

    with h5py.File(path, "w") as h5:
        h5.create_dataset("columns", data=["observations", "actions", "rewards", "terminated"])
        h5.create_dataset("num_episodes", data=1)
        h5.create_dataset("terminated_0", data=True)
        h5.create_dataset("version", data="2.1")
        if consistent:
            n = total // 28 // (1 << 14) * (1 << 14)
            _gzip_zeros(h5, "observations_0", (n, 5), 1 << 14)
            _gzip_zeros(h5, "actions_0", (n, 1), 1 << 14)
            _gzip_zeros(h5, "rewards_0", (n, 1), 1 << 14)
        else:
            h5.create_dataset("observations_0", data=np.zeros((5, 5), np.float32))
            h5.create_dataset("actions_0", data=np.zeros((5, 1), np.float32))
            _gzip_zeros(h5, "rewards_0", (total // 4, 1), 1 << 18)


def policy_dataset(dest: Path) -> None:
    """A cartpole dataset keeping one D4PG behaviour policy (run 0, checkpoint 0), written by
    ``save_snapshot`` as ``rlu generate`` writes it (no env runs)."""
    from rlu.agents import make_agent
    from rlu.data import DatasetWriter, Schema
    from rlu.generate.online import OnlineConfig
    from rlu.generate.policies import policy_stem, save_snapshot
    from rlu.segments import make_episode
    from rlu.tasks import get_task

    task = get_task(TASK)
    small = {"policy_layers": (32, 32), "critic_layers": (32, 32), "torso_hidden": 32}
    online = OnlineConfig("d4pg", episodes=1, agent_overrides=small, policy_dtype="float32")
    agent = make_agent("d4pg", task.observation_spec, task.action_spec, "small", 0, **small)
    work = dest.parent / "policy_work"
    save_snapshot(work, agent, task, online, 0, 0, 0, 0, 0)
    rng = np.random.default_rng(0)
    obs = {k: rng.standard_normal((5, *s.shape)).astype(np.float32)
           for k, s in task.observation_spec.items()}  # fmt: skip
    seg = make_episode(obs, rng.uniform(-1, 1, (4, 1)).astype(np.float32), np.ones(4), False,
                       {"run": 0, "checkpoint": 0})  # fmt: skip
    with DatasetWriter(dest, Schema.for_task(task)) as w:
        w.append(seg)
        for suffix in (".npz", ".json"):
            w.attach(policy_stem(0, 0) + suffix, work / f"checkpoint_00000{suffix}")


POLICY_NPZ = "policies/run_000/checkpoint_00000.npz"


def _rewrite(ds: Path, rel: str, data: bytes) -> None:
    (ds / rel).write_bytes(data)
    m = json.loads((ds / "manifest.json").read_text())
    m["files"][rel] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    (ds / "manifest.json").write_text(json.dumps(m))


def policy_bomb(src: Path, dest: Path, rows: int | None, json_agrees: bool) -> None:
    """A copy of ``src`` whose policy's ``out.weight`` is replaced: ``rows`` x 32 float32 zeros
    deflated (a small file inflating to ``rows`` x 128 bytes), or (``rows`` None) a stored member
    whose header claims 1e12 values; its JSON declaring that shape or the original one."""
    import io
    import zipfile

    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(src, dest)
    with np.load(dest / POLICY_NPZ) as z:
        arrays = {k: z[k] for k in z.files}
    shape = (10**12,) if rows is None else (rows, 32)
    buf = io.BytesIO()
    kind = zipfile.ZIP_STORED if rows is None else zipfile.ZIP_DEFLATED
    with zipfile.ZipFile(buf, "w", kind) as zf:
        for k, v in arrays.items():
            with zf.open(f"{k}.npy", "w", force_zip64=True) as fh:
                if k != "out.weight":
                    np.lib.format.write_array(fh, v)
                    continue
                head = io.BytesIO()
                np.lib.format.write_array_header_1_0(
                    head, {"descr": "<f4", "fortran_order": False, "shape": shape}
                )
                fh.write(head.getvalue())
                left = 4096 if rows is None else rows * 128
                zeros = bytes(16 << 20)
                while left:
                    fh.write(zeros[: min(left, len(zeros))])
                    left -= min(left, len(zeros))
    _rewrite(dest, POLICY_NPZ, buf.getvalue())
    if json_agrees:
        jrel = POLICY_NPZ.replace(".npz", ".json")
        meta = json.loads((dest / jrel).read_text())
        meta["arrays"]["out.weight"]["shape"] = list(shape)
        _rewrite(dest, jrel, json.dumps(meta).encode())


ONLY: list[str] = []


def wanted(label: str) -> bool:
    return not ONLY or any(word in label for word in ONLY)


def measure(label: str, argv: list[str], limit: int = 1800, root: Path = ROOT) -> None:
    """One row: peak RSS, wall time, exit code (124: stopped by ``timeout`` after ``limit`` s)
    and the first line of its error. ``root``: the rlu tree on the path (a baseline's)."""
    if not wanted(label):
        return
    env = {**os.environ, "PYTHONPATH": str(root)}
    for k in ("http_proxy", "https_proxy", "HTTP_PROXY", "HTTPS_PROXY", "all_proxy", "ALL_PROXY"):
        env.pop(k, None)  # the endless server is on 127.0.0.1
    out = subprocess.run(
        ["/usr/bin/time", "-v", "timeout", str(limit), *argv],
        cwd=root,  # python -m puts the working folder first on the path
        env=env,
        capture_output=True,
        text=True,
    )
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", out.stderr).group(1))
    wall = re.search(r"Elapsed \(wall clock\) time.*: (\S+)", out.stderr).group(1)
    last = [ln for ln in out.stderr.splitlines() if ln.startswith("rlu:") or "Error" in ln]
    code = re.search(r"Exit status: (\d+)", out.stderr).group(1)
    print(f"| {label} | {rss / 1024:,.0f} MB | {wall} | {code} | {(last or [''])[0][:90]} |")


def foreign_bombs(work: Path, total: int, rlu: list[str], gib: float) -> None:
    """Issue 30's bomb classes: foreign HDF5 / .npz imports and kept behaviour policies."""
    files = {
        "hdf5_one.hdf5": lambda p: hdf5_one_array_bomb(p, total),
        "hdf5_all.hdf5": lambda p: hdf5_consistent_bomb(p, total),
        "hdf5_valid.hdf5": lambda p: hdf5_consistent_bomb(p, total // 4, episode=1000),
        "npz_all.npz": lambda p: npz_consistent_bomb(p, total),
        "d3rlpy_one.h5": lambda p: d3rlpy_bomb(p, total, consistent=False),
        "d3rlpy_all.h5": lambda p: d3rlpy_bomb(p, total, consistent=True),
    }
    for name, make in files.items():
        if not (work / name).exists():
            make(work / name)
    sizes = {name: (work / name).stat().st_size for name in files}
    print(f"\nforeign files, {gib:g} GiB inflated ({gib / 4:g} GiB for the valid one); on disk "
          f"{sizes}\n")  # fmt: skip
    print("| command | peak RSS | wall | exit | message |\n|---|---:|---:|---:|---|")
    d4rl = [*rlu, "import", "--format", "d4rl", "--task", TASK, "--out", str(work / "out")]
    d3 = [*rlu, "import", "--format", "d3rlpy", "--task", TASK, "--out", str(work / "out")]
    for label, argv in (
        (f"import d4rl .hdf5: rewards a {gib:g} GiB gzip bomb",
         [*d4rl, str(work / "hdf5_one.hdf5")]),
        (f"import d4rl .hdf5: every array gzip, {gib:g} GiB, no episode end",
         [*d4rl, str(work / "hdf5_all.hdf5")]),
        (f"import d4rl .hdf5: every array gzip, {gib / 4:g} GiB of valid 1000-step episodes",
         [*d4rl, str(work / "hdf5_valid.hdf5")]),
        (f"import d4rl .npz: every member deflated, {gib:g} GiB, no episode end",
         [*d4rl, str(work / "npz_all.npz")]),
        (f"import d3rlpy: rewards_0 a {gib:g} GiB gzip bomb",
         [*d3, str(work / "d3rlpy_one.h5")]),
        (f"import d3rlpy: one {gib:g} GiB episode of gzip arrays",
         [*d3, str(work / "d3rlpy_all.h5")]),
    ):  # fmt: skip
        shutil.rmtree(work / "out", ignore_errors=True)
        measure(label, argv)
    shutil.rmtree(work / "out", ignore_errors=True)
    policies = work / "policies_ds"
    if not policies.exists():
        policy_dataset(policies)
    measure("evaluate-behaviour: the policy as written (the baseline: torch, one episode)",
            [*rlu, "evaluate-behaviour", str(policies), "--run", "0", "--checkpoint", "0",
             "--episodes", "1"])  # fmt: skip
    rows = total // 128
    for label, rows_, agrees in (
        ("policy .npz claiming 1e12 values", None, False),
        (f"policy .npz inflating to {gib:g} GiB, its JSON the original", rows, False),
        (f"policy .npz inflating to {gib:g} GiB, its JSON agreeing", rows, True),
    ):
        dest = work / "policy_bomb"
        policy_bomb(policies, dest, rows_, agrees)
        measure(f"evaluate-behaviour: {label}",
                [*rlu, "evaluate-behaviour", str(dest), "--run", "0", "--checkpoint", "0",
                 "--episodes", "1"])  # fmt: skip
        measure(f"validate: {label}", [*rlu, "validate", str(dest)])


def interop(work: Path, total: int, rlu: list[str], gib: float, steps: int, base: Path | None):
    """Issue 39 item 5: Minari bombs (one array, a whole episode, an infos array), an export's
    sidecar bomb, and the peak of exporting a large dataset (D4RL .hdf5 / .npz, d3rlpy, Minari);
    with ``base``, the same exports by that rlu tree, side by side."""
    sys.path.insert(0, str(ROOT))
    from tests.hostile.bombs import large_dataset, minari_bomb, sidecar_bomb

    for old in ("minari_bombs", "sidecar_bomb"):
        shutil.rmtree(work / old, ignore_errors=True)
    print(f"\ninterop: bombs of {gib:g} GiB, exports of {steps:,} steps\n")
    print("| command | peak RSS | wall | exit | message |\n|---|---:|---:|---:|---|")
    for kind in ("rewards", "consistent", "infos"):
        label = f"import minari: {kind} a {gib:g} GiB gzip bomb"
        if not wanted(label):
            continue
        path = minari_bomb(work / "minari_bombs", total, kind)
        shutil.rmtree(work / "out", ignore_errors=True)
        measure(label, [*rlu, "import", str(path), "--format", "minari", "--out",
                        str(work / "out")])  # fmt: skip
    label = f"import d4rl: its sidecar's segment table a {gib:g} GiB deflate bomb"
    if wanted(label):
        out = sidecar_bomb(work / "sidecar_bomb", total)
        shutil.rmtree(work / "out", ignore_errors=True)
        measure(label, [*rlu, "import", str(out), "--format", "d4rl", "--out", str(work / "out")])
    big = work / f"large_{steps}"
    if not big.exists():
        large_dataset(big, steps)
    trees = [("", ROOT)] + ([(f" (baseline {base})", base)] if base else [])
    for name, args in (
        ("d4rl .hdf5", ["--format", "d4rl", "-o", str(work / "x.hdf5")]),
        ("d4rl .npz", ["--format", "d4rl", "-o", str(work / "x.npz")]),
        ("d3rlpy", ["--format", "d3rlpy", "-o", str(work / "x.h5")]),
        ("minari", ["--format", "minari", "--id", "rlu/large-v0", "--minari-dir",
                    str(work / "minari_large")]),
    ):  # fmt: skip
        for tag, tree in trees:
            for p in work.glob("x.*"):
                p.unlink()
            shutil.rmtree(work / "minari_large", ignore_errors=True)
            measure(f"export {steps:,} steps to {name}{tag}", [*rlu, "export", str(big), *args],
                    root=tree)  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workdir", default=None)
    p.add_argument("--gib", type=float, default=2.5, help="inflated size of the gzip bombs")
    p.add_argument("--only", nargs="*", default=[], help="run the commands whose label has one")
    p.add_argument("--steps", type=int, default=4_800_000, help="steps of the large export")
    p.add_argument("--baseline", type=Path, default=None, help="an rlu tree to export with too")
    p.add_argument("--interop-only", action="store_true", help="only the interop section")
    args = p.parse_args()
    ONLY[:] = args.only
    work = Path(args.workdir or tempfile.mkdtemp(prefix="rlu-bombs-"))
    work.mkdir(parents=True, exist_ok=True)
    total = int(args.gib * (1 << 30))
    py = sys.executable
    rlu = [py, "-m", "rlu"]
    if args.interop_only:
        interop(work, total, rlu, args.gib, args.steps, args.baseline)
        return
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
    foreign_bombs(work, total, rlu, args.gib)
    interop(work, total, rlu, args.gib, args.steps, args.baseline)
    if args.workdir is None:
        shutil.rmtree(work)


if __name__ == "__main__":
    main()
