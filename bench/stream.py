"""Stacked Atari transitions from disk (issue 36): the stream sampler, the uniform sampler (today's
path and the new one), and a Dopamine-style in-RAM gather, side by side on real frames.

    PYTHONPATH=. .venv/bin/python bench/stream_data.py --out /tmp/rlu_stream   # the data, once
    PYTHONPATH=. .venv/bin/python bench/stream.py --data /tmp/rlu_stream [--seconds 20]

The data is real game frames written by rlu (``bench/stream_data.py``): ``run`` (the parts
assembled) and its 8 parts ``part0`` .. ``part7`` (the mixture). Every figure runs in a fresh
process (its own peak RSS, from ``getrusage``), one after another; before each cold figure every
file of the datasets it reads is evicted from the page cache (``posix_fadvise(DONTNEED)``; the
files are never mapped by another process). Figures, batch 256 stacked SARSA transitions (4
frames of 84x84, n-step 1):

- ``gather``: numpy fancy indexing from the run's frames decoded into a uint8 buffer in RAM (1M
  frames: 7 GB), state and next state gathered separately, 4 frames each, with actions, rewards
  and terminals (Dopamine's replay; the buffer is filled before the timing starts); timed as
  fancy indexing and as ``np.take``, alternated, the faster the figure;
- ``uniform-today`` / ``uniform``: ``rlu.data.views.Sampler`` over ``TransitionView``, warm (the
  whole frame file read once before timing) and cold; *today* swaps the frame column for this
  file's copy of the reader before issue 36 (one ``pread`` and one ``zlib.decompressobj`` per
  frame in a Python loop), the new one is the store's reader;
- ``stream``: ``rlu.data.StreamSampler`` from a cold disk (time to the first batch: the first
  window decoded; the rate over ``--warmup`` seconds while the rest of the buffer fills ahead,
  then the steady rate over ``--seconds``, still reading the evicted files; the overall rate
  from construction), ``--memory`` bytes of buffer, ``--reuse`` draws per sample;
- ``mixture``: the same over the 8 parts (same frames, same memory), weights by size;
- ``inflate``: frames/s of libdeflate and zlib on one thread over the run's first 20,000 frames.

It prints transitions/s, the ratio to the gather and peak RSS per figure, the machine's load
and cores, and the stream's sampling statistics (distinct episodes per batch, draws per sample)
against the uniform sampler's.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

BATCH = 256


def evict(paths: list[Path]) -> None:
    """Drop every file under ``paths`` from the page cache."""
    for root in paths:
        for f in sorted(root.rglob("*")):
            if f.is_file():
                fd = os.open(f, os.O_RDONLY)
                try:
                    os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
                finally:
                    os.close(fd)


def warm(paths: list[Path]) -> None:
    for root in paths:
        for f in sorted(root.rglob("*")):
            if f.is_file():
                with open(f, "rb") as fh:
                    while fh.read(1 << 24):
                        pass


def peak_mb() -> float:
    """This process's peak RSS plus its frame-inflating helpers' (``rlu.data.store.decoders``)."""
    from rlu.data.store import decoders

    total = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    held = decoders._DECODERS
    for proc, _, _ in held[1].helpers if held is not None and held[1] is not None else ():
        with open(f"/proc/{proc.pid}/status") as fh:
            kb = next(line for line in fh if line.startswith("VmHWM:")).split()[1]
        total += int(kb) / 1024
    return total


def timed(sample, seconds: float, batches: int | None = None) -> tuple[float, int]:
    """(transitions/s, batches) of ``sample()`` over ``seconds`` (or exactly ``batches``)."""
    n, t0 = 0, time.perf_counter()
    while (batches is None and time.perf_counter() - t0 < seconds) or (
        batches is not None and n < batches
    ):
        sample()
        n += 1
    return n * BATCH / (time.perf_counter() - t0), n


# --- today's frame column (the reader before issue 36), for the comparison ------------------
def legacy_column(col):
    """A copy of ``col`` whose ``take`` is the reader's loop before issue 36: one pread and one
    zlib.decompressobj per frame, in row order, every frame decoded afresh."""
    from rlu.data.store.reader import ZlibColumn

    class Today(ZlibColumn):
        def take(self, rows):
            rows = np.asarray(rows, np.int64)
            out = np.empty((*rows.shape, *self.spec.shape), self.dtype)
            flat = out.reshape(-1, self.spec.size)
            fd = self._fileno()
            starts, ends = self.offsets[rows.ravel()], self.offsets[rows.ravel() + 1]
            nbytes = self.frame_bytes
            for j, (a, b) in enumerate(zip(starts.tolist(), ends.tolist(), strict=True)):
                d = zlib.decompressobj()
                raw = d.decompress(os.pread(fd, b - a, a), nbytes)
                ok = len(raw) == nbytes and d.eof and not d.unconsumed_tail and not d.unused_data
                if not ok:
                    raise ValueError(f"frame {int(rows.ravel()[j])}")
                flat[j] = np.frombuffer(raw, self.dtype)
            return out

    return Today(col.path, col.offsets, col.spec)


# --- one figure per process -------------------------------------------------------------------
def figure(name: str, args) -> dict:
    from rlu.data import StreamSampler, TransitionView, open_dataset
    from rlu.data.views import Sampler
    from rlu.types import BatchSpec

    data = Path(args.data)
    run, parts = data / "run", [data / f"part{i}" for i in range(8)]
    out: dict = {"figure": name}
    if name == "inflate":  # frames/s of each inflater on one thread, the same 20k frames
        from rlu.data import inflate

        col = open_dataset(run).column("observation")
        with open(col.path, "rb") as fh:
            data = fh.read(int(col.offsets[20_000]))
        starts, ends = col.offsets[:20_000], col.offsets[1:20_001]
        frames = np.empty((20_000, col.frame_bytes), np.uint8)
        for _ in range(2):  # alternated
            for inflater in inflate.installed():
                with inflate.use(inflater):
                    t0 = time.perf_counter()
                    inflate.inflate_frames(data, starts, ends, frames, col.frame_bytes)
                    out.setdefault(inflater, []).append(20_000 / (time.perf_counter() - t0))
        out = {k: max(v) if isinstance(v, list) else v for k, v in out.items()}
        out["rate"], out["batches"] = out["libdeflate"] / out["zlib"], 0
    elif name == "gather":
        ds = open_dataset(run)
        col = ds.column("observation")
        t0 = time.perf_counter()
        frames = np.empty(col.shape, np.uint8)
        step = 1 << 16
        for a in range(0, len(col), step):
            frames[a : a + step] = col[a : a + step]
        out["fill_s"] = time.perf_counter() - t0
        view = TransitionView(ds)
        # the frame row of each valid transition's step (Dopamine's "valid index" check, done
        # once here), its action, reward and terminal
        seg, t = view.index.locate(np.arange(len(view)))
        row = view.frame_start[seg] + (t - view.start[seg]) + 3
        action = np.asarray(ds.column("action"))
        reward = np.asarray(ds.column("reward"))
        terminal = ~np.asarray(ds.column("discount")).astype(bool)
        rng = np.random.default_rng(0)
        stack = np.arange(-3, 1)

        def fancy():
            i = rng.integers(0, len(row), BATCH)
            r, s = row[i], t[i]
            state, after = frames[r[:, None] + stack], frames[r[:, None] + 1 + stack]
            return state, action[s], reward[s], after, terminal[s]

        def take():  # the same with np.take (the primitive rlu's views and the stream use)
            i = rng.integers(0, len(row), BATCH)
            r, s = row[i], t[i]
            state = np.take(frames, r[:, None] + stack, axis=0)
            after = np.take(frames, r[:, None] + 1 + stack, axis=0)
            return state, action[s], reward[s], after, terminal[s]

        fancy(), take()
        half = args.seconds / 4  # alternated, twice each: the faster form is the figure
        rates = {"fancy": [], "take": []}
        for _ in range(2):
            for name, fn in (("fancy", fancy), ("take", take)):
                rates[name].append(timed(fn, half))
        best = max(rates, key=lambda k: sum(r for r, _ in rates[k]))
        out["form"] = best
        out["forms"] = {k: sum(r for r, _ in v) / len(v) for k, v in rates.items()}
        out["rate"] = out["forms"][best]
        out["batches"] = sum(n for _, n in rates[best])
    elif name.startswith("uniform"):
        cold = name.endswith("cold")
        (evict if cold else warm)([run])
        ds = open_dataset(run)
        if "today" in name:
            ds._cache["observation"] = legacy_column(ds.column("observation"))
        s = Sampler(TransitionView(ds), BATCH, seed=0)
        if cold:  # a fixed number of batches from the evicted file: the cache warms as it reads
            out["rate"], out["batches"] = timed(s.sample, 0, args.cold_batches)
        else:
            s.sample()
            out["rate"], out["batches"] = timed(s.sample, args.seconds)
    elif name in ("stream", "mixture"):
        paths = [run] if name == "stream" else parts
        evict(paths)
        t0 = time.perf_counter()
        s = StreamSampler(paths, BatchSpec(BATCH), seed=0, memory=args.memory, reuse=args.reuse)
        s.sample()
        out["first_s"] = time.perf_counter() - t0
        out["window"], out["memory"] = s.window, args.memory
        # the decoders fill the rest of the buffer ahead of the window first: the steady rate
        # is timed after --warmup seconds (still reading the evicted files: each chunk is read
        # once a pass)
        warm_rate, warm_batches = timed(s.sample, args.warmup)
        out["warmup_rate"] = warm_rate
        out["rate"], out["batches"] = timed(s.sample, args.seconds)
        out["overall"] = (out["batches"] + warm_batches + 1) * BATCH / (time.perf_counter() - t0)
        # sampling statistics over the next batches
        view = TransitionView(open_dataset(run))
        offsets = _part_offsets(parts) if name == "mixture" else [0]
        segs, datasets = [], []
        for _ in range(200):
            _, src = s.sample_sourced()
            ids = src.index + np.asarray(offsets)[src.dataset]
            segs.append(len(np.unique(view.index.locate(ids)[0])))
            datasets.append(len(np.unique(src.dataset)))
        out["episodes_per_batch"] = float(np.mean(segs))
        out["datasets_per_batch"] = float(np.mean(datasets))
        s.close()
    out["peak_rss_mb"] = peak_mb()
    out["load"] = os.getloadavg()[0]
    return out


def _part_offsets(parts: list[Path]) -> list[int]:
    """Each part's first transition id in the assembled run's TransitionView (parts appended
    in order: their segments, and so their transitions, follow each other)."""
    from rlu.data import TransitionView, open_dataset

    sizes = [len(TransitionView(open_dataset(p))) for p in parts]
    return np.concatenate([[0], np.cumsum(sizes)[:-1]]).tolist()


def uniform_statistics(run: Path, window_batches: int = 200) -> dict:
    from rlu.data import TransitionView, open_dataset

    view = TransitionView(open_dataset(run))
    rng = np.random.default_rng(0)
    segs = [len(np.unique(view.index.locate(rng.integers(0, len(view), BATCH))[0]))
            for _ in range(window_batches)]  # fmt: skip
    n = len(view)
    counts = np.bincount(rng.integers(0, n, n), minlength=n)
    return {"episodes_per_batch": float(np.mean(segs)), "never_drawn": float((counts == 0).mean()),
            "episodes": int(open_dataset(run).num_segments)}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="bench/stream_data.py's --out")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--cold-batches", type=int, default=100)
    ap.add_argument("--warmup", type=float, default=15.0, help="stream: seconds before timing")
    ap.add_argument("--memory", type=int, default=2 << 30)
    ap.add_argument("--reuse", type=int, default=8)
    ap.add_argument("--figures", default="gather,uniform-today,uniform-today-cold,uniform,"
                    "uniform-cold,stream,mixture")  # fmt: skip
    ap.add_argument("--figure", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.figure:
        print(json.dumps(figure(args.figure, args)))
        return
    from rlu.data import open_dataset
    from rlu.data.inflate import current
    from rlu.system import available_cores

    run = Path(args.data) / "run"
    ds = open_dataset(run)
    z = (run / "steps" / "observation.zlib").stat().st_size
    print(f"data: {run}, {ds.num_steps:,} steps, {ds.num_segments:,} episodes, "
          f"{ds.num_frames:,} frames, {z / ds.num_frames:,.0f} B a frame (zlib), "
          f"{z / 1e9:.2f} GB; inflater {current()}; {available_cores()} cores, load "
          f"{os.getloadavg()[0]:.1f}")  # fmt: skip
    results = {}
    for name in args.figures.split(","):
        cmd = [sys.executable, __file__, "--figure", name, "--data", args.data,
               "--seconds", str(args.seconds), "--cold-batches", str(args.cold_batches),
               "--warmup", str(args.warmup),
               "--memory", str(args.memory), "--reuse", str(args.reuse)]  # fmt: skip
        res = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ})
        if res.returncode:
            print(f"{name}: failed\n{res.stderr[-3000:]}")
            continue
        results[name] = r = json.loads(res.stdout.strip().splitlines()[-1])
        if name == "inflate":
            print(f"  inflate: one thread, 20,000 frames: libdeflate {r['libdeflate']:,.0f} "
                  f"frames/s, zlib {r['zlib']:,.0f} frames/s = {r['rate']:.2f}x, load "
                  f"{r['load']:.1f}")  # fmt: skip
            results.pop(name)
            continue
        extra = ""
        if "first_s" in r:
            extra = (f", first batch after {r['first_s']:.1f} s (window {r['window']:,}), "
                     f"{r['warmup_rate']:,.0f}/s in the first {args.warmup:.0f} s, overall "
                     f"{r['overall']:,.0f}/s, {r['episodes_per_batch']:.0f} episodes and "
                     f"{r['datasets_per_batch']:.1f} datasets a batch")  # fmt: skip
        if "fill_s" in r:
            forms = r["forms"]
            extra = (f", buffer filled in {r['fill_s']:.0f} s; fancy indexing "
                     f"{forms['fancy']:,.0f}/s, np.take {forms['take']:,.0f}/s")  # fmt: skip
        print(f"  {name:20s} {r['rate']:10,.0f} transitions/s ({r['batches']} batches), peak RSS "
              f"{r['peak_rss_mb']:,.0f} MB, load {r['load']:.1f}{extra}", flush=True)  # fmt: skip
    base = results.get("gather", {}).get("rate")
    print(f"\n{'figure':20s} {'transitions/s':>14s} {'/ gather':>9s} {'peak RSS MB':>12s}")
    for name, r in results.items():
        ratio = f"{r['rate'] / base:8.2f}x" if base else ""
        print(f"{name:20s} {r['rate']:14,.0f} {ratio:>9s} {r['peak_rss_mb']:12,.0f}")
    for a, b in (("uniform", "uniform-today"), ("uniform-cold", "uniform-today-cold"),
                 ("mixture", "stream")):  # fmt: skip
        if a in results and b in results:
            print(f"{a} / {b}: {results[a]['rate'] / results[b]['rate']:.2f}x")
    u = uniform_statistics(run)
    print(
        f"uniform sampler: {u['episodes_per_batch']:.0f} distinct episodes a batch (of "
        f"{u['episodes']:,}); per pass of len(view) draws, {u['never_drawn']:.0%} of the "
        f"samples never drawn (stream: each drawn exactly --reuse={args.reuse} times a pass)"
    )


if __name__ == "__main__":
    main()
