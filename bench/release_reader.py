"""Our release reader vs TensorFlow on the same gzip shards of control-suite seq2 windows.

    .venv/bin/python bench/release_reader.py [--records 800000] [--shards 4] [--decoders] [--png]
                                             [--atari]

Writes ``--shards`` gzip TFRecord shards in the exact ``dm_control_suite/cartpole_swingup`` schema
(237-byte Examples, as the TF-written fixture), then times, in one run:

- rlu: framing + CRC only; framing + columnar Example decoding; the full loader-shaped parse
  (``families.iter_raw``); conversion into the store (1 and 2 processes);
- TensorFlow (in its own venv, never a dependency of rlu; ``--tf`` names its python):
  the original loader's pipeline (``dm_control_suite.py``: TFRecordDataset, interleave with block
  length 5, shuffle, ``parse_single_example`` per record, shuffle, batch) and TF's fastest form
  (TFRecordDataset, batch, then ``parse_example`` on the batch);
- ``--decoders``: the protobuf runtime (upb, with our own Example descriptor) vs the hand-written
  decoder, record by record and in batches;
- ``--png``: Pillow vs zlib inflate alone on 84x84 grey frames;
- ``--atari``: converting Atari transition shards (Pong-like frames, 8 PNGs per record, zlib
  in the store) with 1 and 2 processes.

Prints records/s and MB/s (of the decompressed record stream) and the ratios.

``--inflate`` (issue 36) runs only this: on one core (the process pinned to one CPU), on the same
bytes, zlib's bare inflate of the file and the installed inflater's (the bounds: libdeflate in one
call for a member inflating to under 64 MiB, zlib-ng streamed over it), and the release reader
(framing + both CRCs of every record; also without the CRCs, and with zlib as its inflater), with
the ratios to both bounds. Shards: gzip shards of Atari transitions (8 PNG frames a record; real
frames with ``--frames DATASET``, e.g. ``bench/stream_data.py``'s ``run``), one inflating to under
64 MiB and one over it, and one of control-suite windows (237-byte records: the per-record cost).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
KEYS = {  # key -> values per step (cartpole_swingup, docs/release_format.md §3.3)
    "observation/position": 3,
    "observation/velocity": 2,
    "action": 1,
    "discount": 1,
    "reward": 1,
    "episodic_reward": 1,
    "step_type": 1,
}
SCALARS = ("discount", "reward", "episodic_reward", "step_type")
CPU_NOTES: list[str] = []


# --- TensorFlow side (runs under the TF venv's python) ---------------------------------------


def tf_worker(files: list[str], mode: str, batch: int, shuffle: int) -> dict:
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    import tensorflow as tf

    spec = {
        k: tf.io.FixedLenSequenceFeature(
            [] if k in SCALARS else [d], tf.float32, allow_missing=True
        )
        for k, d in KEYS.items()
    }
    if mode == "original":
        # dm_control_suite.py: file list, interleave (block 5), shuffle, parse per record, batch
        ds = tf.data.Dataset.from_tensor_slices(files)
        ds = ds.interleave(
            lambda f: tf.data.TFRecordDataset(f, compression_type="GZIP"),
            cycle_length=tf.data.AUTOTUNE,
            block_length=5,
            num_parallel_calls=tf.data.AUTOTUNE,
        )
        ds = ds.shuffle(shuffle)
        ds = ds.map(
            lambda r: tf.io.parse_single_example(r, spec), num_parallel_calls=tf.data.AUTOTUNE
        )
        ds = ds.shuffle(batch * 10)
        ds = ds.batch(batch)
    else:
        # the fastest form: read, batch raw records, parse a whole batch at once
        ds = tf.data.TFRecordDataset(files, compression_type="GZIP", num_parallel_reads=len(files))
        ds = ds.batch(batch)
        ds = ds.map(lambda r: tf.io.parse_example(r, spec), num_parallel_calls=tf.data.AUTOTUNE)
    ds = ds.prefetch(tf.data.AUTOTUNE)
    t0 = time.perf_counter()
    n = 0
    for b in ds:
        n += int(b["reward"].shape[0])
    return {"records": n, "seconds": time.perf_counter() - t0, "tf": tf.__version__}


# --- rlu side --------------------------------------------------------------------------------


def make_shards(folder: str, records: int, shards: int) -> list[str]:
    import numpy as np

    from rlu.data.release import families as Fm

    rng = np.random.default_rng(0)
    files = []
    per = records // shards
    for s in range(shards):
        path = os.path.join(
            folder, "dm_control_suite", "cartpole_swingup", f"train-{s:05d}-of-{shards:05d}"
        )
        os.makedirs(os.path.dirname(path), exist_ok=True)
        recs = []
        for i in range(per):
            st = [0.0, 1.0] if i % 500 == 0 else ([1.0, 2.0] if i % 500 == 499 else [1.0, 1.0])
            rec = {k: rng.standard_normal((2, d)).astype(np.float32) for k, d in KEYS.items()}
            for k in SCALARS:
                rec[k] = rec[k][:, 0]
            rec["step_type"] = np.float32(st)
            rec["discount"] = np.ones(2, np.float32)
            recs.append(rec)
        Fm.write_shard(path, "dm_control_suite", recs)
        files.append(path)
    return files


def time_it(fn, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def rlu_rows(
    files: list[str], stream_bytes: int, records: int, tmp: str
) -> list[tuple[str, float]]:
    from rlu.codecs import example as E
    from rlu.data.release import families as Fm
    from rlu.data.release.convert import convert
    from rlu.data.release.framing import RecordReader

    def framing():
        n = 0
        for f in files:
            for b in RecordReader(f).batches():
                n += len(b)
        assert n == records

    def columns():
        n = 0
        for f in files:
            pending: list[bytes] = []
            for b in RecordReader(f).batches():
                pending.extend(b)
                while len(pending) >= 4096:
                    cols = E.decode_batch(pending[:4096])
                    pending = pending[4096:]
                    n += cols["reward"].shape[0]
            if pending:
                n += E.decode_batch(pending)["reward"].shape[0]
        assert n == records

    def parsed():
        n = 0
        for f in files:
            for raw in Fm.iter_raw(f, "dm_control_suite"):
                n += raw["reward"].shape[0]
        assert n == records

    def framing_prefetch():
        for f in files:
            for _ in RecordReader(f, prefetch=True).batches():
                pass

    rows = [
        ("rlu framing + CRC", time_it(framing)),
        ("rlu framing + CRC, inflate in a second thread", time_it(framing_prefetch)),
        ("rlu framing + CRC + Example columns", time_it(columns)),
        ("rlu loader-shaped arrays (iter_raw)", time_it(parsed)),
    ]
    for w in (1, 2):
        out = os.path.join(tmp, f"converted{w}")

        def conv(w=w, out=out):
            import shutil

            if os.path.exists(out):
                shutil.rmtree(out)
            convert(files, "dm_control_suite", "control_suite/cartpole_swingup", out, workers=w)

        import resource

        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        me0 = resource.getrusage(resource.RUSAGE_SELF)
        secs = time_it(conv, 1)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        me1 = resource.getrusage(resource.RUSAGE_SELF)
        cpu_children = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
        cpu_self = (me1.ru_utime + me1.ru_stime) - (me0.ru_utime + me0.ru_stime)
        label = f"rlu convert into the store, {w} process{'es' if w > 1 else ''}"
        rows.append((label, secs))
        CPU_NOTES.append(
            f"{label}: {secs:.2f} s wall, CPU {cpu_self:.2f} s parent"
            f" + {cpu_children:.2f} s readers"
        )
    return rows


def atari_frames(n: int):
    """Pong-like 84x84 grey frames: flat court, two paddles and a ball that move, a score."""
    import numpy as np

    frames = np.full((n, 84, 84), 87, np.uint8)
    frames[:, 10:12, :] = 236  # walls
    frames[:, 74:76, :] = 236
    t = np.arange(n)
    for i in range(n):
        y1, y2 = 14 + (t[i] * 3) % 54, 14 + (t[i] * 2 + 20) % 54
        frames[i, y1 : y1 + 6, 8:10] = 147
        frames[i, y2 : y2 + 6, 74:76] = 92
        bx, by = 12 + (t[i] * 5) % 60, 14 + (t[i] * 7) % 58
        frames[i, by : by + 2, bx : bx + 1] = 236
        frames[i, 2:8, 20 + (i // 500) % 10 : 24 + (i // 500) % 10] = 236  # a score digit
    return frames


def atari_rows(tmp: str, records: int = 8000, shards: int = 4) -> list[tuple[str, float, int]]:
    """Conversion of Atari transition shards (PNG decode, then zlib for the store), 1 vs 2."""
    import shutil

    import numpy as np

    from rlu.data.release import families as Fm
    from rlu.data.release.convert import convert

    frames = atari_frames(records + 4)
    stack = lambda i: np.stack([frames[i + k] for k in range(4)], -1)  # noqa: E731
    files, per = [], records // shards
    for s in range(shards):
        path = os.path.join(tmp, "atari", "Pong", f"run_1-{s:05d}-of-{shards:05d}")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        recs = [
            dict(o_t=stack(i), o_tp1=stack(i + 1), a_t=i % 6, a_tp1=(i + 1) % 6,
                 r_t=np.float32(0), d_t=np.float32(1), episode_id=i // 1000,
                 episode_return=np.float32(0))
            for i in range(s * per, (s + 1) * per)
        ]  # fmt: skip
        Fm.write_shard(path, "atari", recs)
        files.append(path)
    rows = []
    for w in (1, 2):
        out = os.path.join(tmp, f"atari_converted{w}")

        def conv(w=w, out=out):
            if os.path.exists(out):
                shutil.rmtree(out)
            convert(files, "atari", "atari/Pong", out, workers=w)

        label = f"rlu convert Atari transitions, {w} process{'es' if w > 1 else ''}"
        rows.append((label, time_it(conv, 2), per * shards))
    return rows


def inflate_rows(
    tmp: str,
    frames_from: str | None,
    records: tuple[int, ...] = (3000, 12000),
    windows: int = 100_000,
    rounds: int = 7,
):
    """(shard, {figure: MB/s of the inflated stream}) on one core, on the same bytes: zlib's and
    the installed inflater's bare inflate of the file (the bounds), and the release reader
    (framing + both CRCs of every record; also without the CRCs, and with zlib as its inflater).
    The figures are taken in interleaved rounds, the best of ``rounds`` each, so that a load
    that comes and goes on a shared machine weighs on all of them alike."""
    import zlib

    import numpy as np

    from rlu.data import inflate
    from rlu.data.release import families as Fm
    from rlu.data.release.framing import RecordReader

    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    if frames_from:
        from rlu.data import open_dataset

        col = open_dataset(frames_from).column("observation")
        frames = col[: max(records) + 8]
    else:
        frames = atari_frames(max(records) + 8)
    stack = lambda i: np.stack([frames[i + k] for k in range(4)], -1)  # noqa: E731
    shards = []
    for n in records:
        path = os.path.join(tmp, "inflate", "MsPacman", f"run_1-00000-of-00001-{n}")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        recs = [dict(o_t=stack(i), o_tp1=stack(i + 1), a_t=i % 6, a_tp1=(i + 1) % 6,
                     r_t=np.float32(0), d_t=np.float32(1), episode_id=i // 1000,
                     episode_return=np.float32(0)) for i in range(n)]  # fmt: skip
        Fm.write_shard(path, "atari", recs)
        shards.append((f"{n:,} Atari transitions", path))
    if windows:
        (path,) = make_shards(os.path.join(tmp, "inflate"), windows, 1)
        shards.append((f"{windows:,} control-suite windows (237 B records)", path))
    out = []
    for name, path in shards:
        with open(path, "rb") as fh:
            data = fh.read()
        size = int.from_bytes(data[-4:], "little")

        def read_all(path=path, size=size, **kw):
            reader = RecordReader(path, **kw)
            for _ in reader.batches():
                pass
            assert reader.stats.bytes_read == size and not reader.stats.skipped

        def with_zlib(path=path):
            with inflate.use("zlib"):
                read_all(path)

        def stream(make, data=data, size=size):
            d, total, view = make(), 0, data
            while view:
                got = d.decompress(view, 1 << 22)
                total += len(got)
                view = d.unconsumed_tail
                if d.eof:
                    break
            assert total == size

        whole = size <= inflate.WHOLE_GZIP_MAX and inflate.current() == "libdeflate"
        bound = "libdeflate, one call" if whole else f"{inflate.gzip_inflater()}, streamed"
        runs = {
            "bare inflate, zlib": lambda: stream(lambda: zlib.decompressobj(31)),
            f"bare inflate, {bound}": (
                (lambda data=data: inflate.gunzip_whole(data))
                if whole
                else (lambda: stream(inflate.gzip_decompressobj))
            ),
            f"rlu reader, {bound}": read_all,
            f"rlu reader, {bound}, no CRC checks": lambda: read_all(verify=False),
            "rlu reader, zlib": with_zlib,
        }
        best = dict.fromkeys(runs, float("inf"))
        for _ in range(rounds):
            for key, fn in runs.items():
                t0 = time.perf_counter()
                fn()
                best[key] = min(best[key], time.perf_counter() - t0)
        label = f"{name}: {len(data) / 1e6:.1f} MB gzip, {size / 1e6:.0f} MB inflated"
        out.append((label, {k: size / v / 1e6 for k, v in best.items()}))
    return out


def decoder_rows(files: list[str], n: int = 50_000) -> list[tuple[str, float, int]]:
    import numpy as np
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    from rlu.codecs import example as E
    from rlu.data.release.framing import RecordReader

    recs = []
    for b in RecordReader(files[0]).batches():
        recs.extend(b)
        if len(recs) >= n:
            break
    recs = recs[:n]

    # Our own Example / Features / Feature messages for the protobuf runtime (no TF).
    fdp = descriptor_pb2.FileDescriptorProto(
        name="rlu_example.proto", package="rlu_bench", syntax="proto3"
    )

    def msg(name, fields):
        m = fdp.message_type.add(name=name)
        for fname, num, ftype, label, tname in fields:
            f = m.field.add(name=fname, number=num, type=ftype, label=label)
            if tname:
                f.type_name = tname
        return m

    T = descriptor_pb2.FieldDescriptorProto
    msg("BytesList", [("value", 1, T.TYPE_BYTES, T.LABEL_REPEATED, None)])
    msg("FloatList", [("value", 1, T.TYPE_FLOAT, T.LABEL_REPEATED, None)])
    msg("Int64List", [("value", 1, T.TYPE_INT64, T.LABEL_REPEATED, None)])
    feat = msg(
        "Feature",
        [
            ("bytes_list", 1, T.TYPE_MESSAGE, T.LABEL_OPTIONAL, ".rlu_bench.BytesList"),
            ("float_list", 2, T.TYPE_MESSAGE, T.LABEL_OPTIONAL, ".rlu_bench.FloatList"),
            ("int64_list", 3, T.TYPE_MESSAGE, T.LABEL_OPTIONAL, ".rlu_bench.Int64List"),
        ],
    )
    del feat
    fs = fdp.message_type.add(name="Features")
    entry = fs.nested_type.add(name="FeatureEntry")
    entry.options.map_entry = True
    entry.field.add(name="key", number=1, type=T.TYPE_STRING, label=T.LABEL_OPTIONAL)
    entry.field.add(
        name="value",
        number=2,
        type=T.TYPE_MESSAGE,
        label=T.LABEL_OPTIONAL,
        type_name=".rlu_bench.Feature",
    )
    fs.field.add(
        name="feature",
        number=1,
        type=T.TYPE_MESSAGE,
        label=T.LABEL_REPEATED,
        type_name=".rlu_bench.Features.FeatureEntry",
    )
    msg("Example", [("features", 1, T.TYPE_MESSAGE, T.LABEL_OPTIONAL, ".rlu_bench.Features")])
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    Example = message_factory.GetMessageClass(pool.FindMessageTypeByName("rlu_bench.Example"))

    def pb():
        for r in recs:
            ex = Example()
            ex.ParseFromString(r)
            out = {}
            for k, f in ex.features.feature.items():
                kind = f.WhichOneof("kind") if False else None
                del kind
                if f.HasField("float_list"):
                    out[k] = np.array(f.float_list.value, np.float32)
                elif f.HasField("int64_list"):
                    out[k] = np.array(f.int64_list.value, np.int64)
                else:
                    out[k] = list(f.bytes_list.value)

    # sanity: both decoders agree on the first record
    ex = Example()
    ex.ParseFromString(recs[0])
    ours = E.decode_example(recs[0])
    for k, f in ex.features.feature.items():
        assert np.array_equal(np.array(f.float_list.value, np.float32), ours[k])

    def hand():
        for r in recs:
            E.decode_example(r)

    def batch():
        for i in range(0, len(recs), 4096):
            E.decode_batch(recs[i : i + 4096])

    def pb_parse_only():
        for r in recs:
            Example().ParseFromString(r)

    return [
        ("protobuf runtime (upb), parse only", time_it(pb_parse_only), len(recs)),
        ("protobuf runtime (upb), parse + numpy arrays", time_it(pb), len(recs)),
        ("hand-written decoder, record by record", time_it(hand), len(recs)),
        ("hand-written decoder, columnar batches", time_it(batch), len(recs)),
    ]


def png_rows() -> list[tuple[str, float, int]]:
    import io
    import zlib

    import numpy as np
    from PIL import Image

    from rlu.codecs.png import decode_png

    rng = np.random.default_rng(0)
    frames = []
    for i in range(200):  # noise and Pong-like rectangles, Paeth-filtered by Pillow's encoder
        img = (
            rng.integers(0, 256, (84, 84), dtype=np.uint8)
            if i % 2
            else np.zeros((84, 84), np.uint8)
        )
        if i % 2 == 0:
            img[20:30, 10:14] = 200
            img[40:44, 40:44] = 255
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, format="PNG")
        frames.append(buf.getvalue())

    def pil():
        for f in frames:
            decode_png(f, 1)

    def pil_open():
        for f in frames:
            np.asarray(Image.open(io.BytesIO(f), formats=("PNG",)))

    def inflate():
        for f in frames:
            zlib.decompress(f[41:-12])

    return [
        ("Pillow Image.open + np.asarray (84x84 grey)", time_it(pil_open), len(frames)),
        ("rlu decode_png: Pillow's C decoder direct (84x84 grey)", time_it(pil), len(frames)),
        ("zlib inflate alone (lower bound)", time_it(inflate), len(frames)),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--records", type=int, default=800_000)
    ap.add_argument("--shards", type=int, default=4)
    ap.add_argument("--tf", default=os.path.join(ROOT, ".venv-tf", "bin", "python"))
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--shuffle", type=int, default=100_000, help="the original loader's buffer")
    ap.add_argument("--decoders", action="store_true")
    ap.add_argument("--png", action="store_true")
    ap.add_argument("--atari", action="store_true", help="also convert Atari transition shards")
    ap.add_argument("--inflate", action="store_true", help="only the one-core inflate figures")
    ap.add_argument("--frames", default=None, help="--inflate: a dataset of real Atari frames")
    ap.add_argument("--tf-worker", nargs=2, metavar=("MODE", "FILES_JSON"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.tf_worker:
        mode, files = args.tf_worker
        print(json.dumps(tf_worker(json.loads(files), mode, args.batch, args.shuffle)))
        return
    if args.inflate:
        sys.path.insert(0, ROOT)
        from rlu.data import inflate

        with tempfile.TemporaryDirectory() as tmp:
            whole = inflate.WHOLE_GZIP_MAX >> 20
            print(
                f"inflaters installed: {inflate.current()} (whole members up to {whole} MiB), "
                f"{inflate.gzip_inflater()} (streams)"
            )
            for label, fig in inflate_rows(tmp, args.frames):
                print(f"\n{label} (one core; load {os.getloadavg()[0]:.1f})")
                zlib_bound, own = list(fig.values())[:2]
                for name, mbs in fig.items():
                    print(
                        f"  {name:48s} {mbs:8.1f} MB/s  {mbs / zlib_bound:5.2f}x zlib's inflate"
                        f"  {mbs / own:5.2f}x the installed inflater's"
                    )
        return

    sys.path.insert(0, ROOT)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        files = make_shards(tmp, args.records, args.shards)
        records = (args.records // args.shards) * args.shards
        gz = sum(os.path.getsize(f) for f in files)
        stream = records * (237 + 16)
        print(
            f"{records:,} records in {len(files)} gzip shards: {gz / 1e6:.1f} MB on disk, "
            f"{stream / 1e6:.1f} MB of records (written in {time.perf_counter() - t0:.0f} s)"
        )
        rows = [(name, s) for name, s in rlu_rows(files, stream, records, tmp)]
        tf_rows = []
        if os.path.exists(args.tf):
            for mode, label in (
                ("original", "TF original loader pipeline"),
                ("fastest", "TF fastest form (batch, parse_example)"),
            ):
                out = subprocess.run(
                    [
                        args.tf,
                        os.path.abspath(__file__),
                        "--tf-worker",
                        mode,
                        json.dumps(files),
                        "--batch",
                        str(args.batch),
                        "--shuffle",
                        str(args.shuffle),
                    ],
                    capture_output=True,
                    text=True,
                    check=True,
                )
                res = json.loads(out.stdout.strip().splitlines()[-1])
                assert res["records"] == records, res
                tf_rows.append((f"{label} (TF {res['tf']})", res["seconds"]))
        else:
            print(f"(no TensorFlow venv at {args.tf}: TF rows skipped)")
        print(f"\n{'reader':58s} {'records/s':>12s} {'MB/s':>8s}")
        for name, s in tf_rows + rows:
            print(f"{name:58s} {records / s:12,.0f} {stream / s / 1e6:8.1f}")
        if tf_rows:
            orig, fast = tf_rows[0][1], tf_rows[1][1]
            print()
            for name, s in rows:
                print(f"{name:58s} {orig / s:6.1f}x original pipeline  {fast / s:5.2f}x TF fastest")
        for note in CPU_NOTES:
            print(note)
        print(f"load average during the run: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        if args.decoders:
            print(f"\n{'Example decoder':58s} {'records/s':>12s}")
            for name, s, n in decoder_rows(files):
                print(f"{name:58s} {n / s:12,.0f}")
        if args.atari:
            print(f"\n{'Atari transitions (4+4 PNG frames per record)':58s} {'records/s':>12s}")
            arows = atari_rows(tmp)
            for name, s, n in arows:
                print(f"{name:58s} {n / s:12,.0f}")
            print(f"{'2 processes / 1 process':58s} {arows[0][1] / arows[1][1]:11.2f}x")
        if args.png:
            print(f"\n{'PNG':58s} {'us/frame':>12s}")
            for name, s, n in png_rows():
                print(f"{name:58s} {s / n * 1e6:12.1f}")


if __name__ == "__main__":
    main()
