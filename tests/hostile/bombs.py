"""Small files that declare gigabytes, for the interop bombs (tests/hostile/test_interop_bombs.py
and bench/hostile_memory.py): Minari datasets whose gzip arrays inflate to ``total`` bytes, and
an export's sidecar whose segment table does. No pytest here: the bench imports it."""

from __future__ import annotations

import io
import zipfile
import zlib
from pathlib import Path

import numpy as np

TASK = "control_suite/cartpole_swingup"


def gzip_zeros(f, name: str, shape: tuple, chunk_rows: int, dtype: str = "f4") -> None:
    """A gzip dataset of zeros written chunk by chunk from one compressed chunk (each chunk of
    a MiB stores about a kB: near zlib's limit, so the size checks of rlu.data.foreign pass)."""
    if name in f:
        del f[name]
    chunks = (chunk_rows, *shape[1:])
    ds = f.create_dataset(name, shape=shape, dtype=dtype, chunks=chunks, compression="gzip")
    blob = zlib.compress(bytes(int(np.prod(chunks)) * np.dtype(dtype).itemsize), 9)
    for i in range(0, shape[0] - chunk_rows + 1, chunk_rows):
        ds.id.write_direct_chunk((i, *([0] * (len(shape) - 1))), blob)


def minari_bomb(root: Path, total: int, kind: str) -> Path:
    """A Minari dataset (rlu's export of one cartpole episode, under ``root``) whose episode
    declares ``total`` bytes of gzip zeros: ``rewards`` alone, every array of the episode
    (``consistent``: one episode of ``total`` / 36 steps), or one ``infos`` array."""
    import h5py

    from rlu.data import Schema, open_dataset
    from rlu.data.minari import export_minari
    from rlu.data.synthetic import write_synthetic
    from rlu.tasks import get_task

    src = write_synthetic(root / f"src_{kind}", Schema.for_task(get_task(TASK)), 1, 5, seed=0)
    path = export_minari(open_dataset(src), f"rlu/bomb-{kind}-v0", root=root / "minari")
    with h5py.File(path / "data" / "main_data.hdf5", "a") as f:
        g = f["episode_0"]
        rows = 1 << 14
        if kind == "rewards":
            gzip_zeros(g, "rewards", (total // 8 // rows * rows,), rows, "f8")
        elif kind == "consistent":
            n = total // 36 // rows * rows  # 3 + 2 observation floats, 1 action, 1 reward, 2 flags
            gzip_zeros(g, "observations/position", (n + 1, 3), rows)
            gzip_zeros(g, "observations/velocity", (n + 1, 2), rows)
            arrays = [("actions", (n, 1), "f4"), ("rewards", (n,), "f4")]
            arrays += [("terminations", (n,), "u1"), ("truncations", (n,), "u1")]
            for name, shape, dtype in arrays:
                gzip_zeros(g, name, shape, rows, dtype)
            g.attrs["total_steps"] = n  # a consistent episode of n steps
        else:  # 6 rows (one per observation) of total / 24 floats, in chunks of 1 MiB
            cols = total // 24 // (1 << 18) * (1 << 18)
            ds = g.create_dataset("infos/bomb", shape=(6, cols), dtype="f4",
                                  chunks=(1, 1 << 18), compression="gzip")  # fmt: skip
            blob = zlib.compress(bytes(4 << 18), 9)
            for r in range(6):
                for c in range(0, cols, 1 << 18):
                    ds.id.write_direct_chunk((r, c), blob)
    return path


def sidecar_bomb(folder: Path, total: int) -> Path:
    """rlu's D4RL export of a small dataset, its sidecar's ``segments/length`` replaced by a
    deflated member declaring ``total`` bytes of zeros. Returns the exported file."""
    from rlu.data import Schema, open_dataset
    from rlu.data.d4rl import export_d4rl
    from rlu.data.synthetic import write_synthetic
    from rlu.tasks import get_task

    src = write_synthetic(folder / "src", Schema.for_task(get_task(TASK)), 2, 5, seed=0)
    out = export_d4rl(open_dataset(src), folder / "x.hdf5")
    side = out.with_name(out.name + ".rlu.npz")
    with zipfile.ZipFile(side) as z:
        members = {i.filename: z.read(i) for i in z.infolist()}
    zeros = bytes(16 << 20)
    with zipfile.ZipFile(side, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as z:
        for name, data in members.items():
            if name != "segments/length.npy":
                z.writestr(name, data)
                continue
            head = io.BytesIO()
            n = total // 8
            np.lib.format.write_array_header_1_0(
                head, {"descr": "<i8", "fortran_order": False, "shape": (n,)}
            )
            with z.open(name, "w", force_zip64=True) as fh:
                fh.write(head.getvalue())
                left = n * 8
                while left:
                    fh.write(zeros[: min(left, len(zeros))])
                    left -= min(left, len(zeros))
    return out


def large_dataset(dest: Path, steps: int) -> Path:
    """A cartpole dataset of ``steps`` steps in 1000-step episodes (random arrays), for the
    peak memory of a large export."""
    from rlu.data import DatasetWriter, Schema
    from rlu.data.synthetic import random_episodes
    from rlu.tasks import get_task

    schema = Schema.for_task(get_task(TASK))
    with DatasetWriter(dest, schema, {"source": "synthetic"}) as w:
        done = 0
        while done < steps:
            n = min(100, (steps - done) // 1000 or 1)
            w.extend(random_episodes(schema, n, 999, seed=done, terminal_prob=0.0))
            done += n * 1000
    return dest
