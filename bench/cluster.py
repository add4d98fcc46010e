"""The release on a cluster, and one full-size Atari run out of core (issue 33).

    PYTHONPATH=. .venv/bin/python bench/cluster.py shards  # one shard job per core: steps/s,
                                                           # peak RSS; assembly MB/s; a run
    PYTHONPATH=. .venv/bin/python bench/cluster.py ray     # a Ray cluster on 127.0.0.1: shards/s
                                                           # per node, the local bytes, a node
                                                           # removed mid-job
    PYTHONPATH=. .venv/bin/python bench/cluster.py ooc     # a 50M-step Atari run: open time,
                                                           # stacked-frame sampling, RSS, disk

Frames are real: ALE games through rlu's env (Dopamine's preprocessing, 84x84 grey, sticky
actions) under a uniform random policy, cut into episodes as the env ends them. Release-format
shards are ``atari_episodes_ordered`` records of those episodes with their frames PNG-encoded by
Pillow (adaptive row filters, as the release's own encoder uses filters; rlu's test encoder
writes filter 0 only). Every big file is deleted once measured (``--keep`` keeps the work dir).
"""

from __future__ import annotations

import argparse
import io
import json
import multiprocessing as mp
import os
import resource
import shutil
import sys
import tempfile
import threading
import time
import zlib
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rlu.codecs import example as ex  # noqa: E402
from rlu.data.release.convert import convert  # noqa: E402
from rlu.data.release.framing import RecordWriter  # noqa: E402
from rlu.data.release.jobs import DatasetJob, convert_release, parts_folder  # noqa: E402
from rlu.workers import Backend  # noqa: E402

RUN_STEPS = 50_000_000  # one Atari run of the release (docs/release_format.md §5)
SHARD_STEPS = 1_000_000  # one atari_episodes_ordered shard: one checkpoint's 1M steps


def rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def rss_parts() -> str:
    """Resident memory split: anonymous (the process's own) and file-backed (mapped columns,
    pages the kernel can drop at any time)."""
    got = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(("RssAnon:", "RssFile:")):
                got[line.split(":")[0]] = int(line.split()[1]) / 1024
    return (
        f"RSS {rss_mb():.0f} MB (anonymous {got['RssAnon']:.0f}, file-backed {got['RssFile']:.0f})"
    )


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def load() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


# --- real frames -----------------------------------------------------------------------------


def real_episodes(game: str, steps: int, work: Path, seed: int = 0) -> list[dict[str, np.ndarray]]:
    """``steps`` env steps of ``game`` as episodes (frames, actions, rewards, discounts), cached
    in ``work``."""
    cache = work / f"frames_{game}_{steps}_{seed}.npz"
    if not cache.exists():
        import rlu

        env = rlu.make_env(f"atari/{game}")
        rng = np.random.default_rng(seed)
        obs, _ = env.reset(seed=seed)
        frames, acts, rews, ends = [np.asarray(obs)[..., -1]], [], [], []
        for _ in range(steps):
            a = int(rng.integers(env.action_space.n))
            obs, r, term, trunc, _ = env.step(a)
            acts.append(a)
            rews.append(r)
            ends.append(2 if term else 1 if trunc else 0)
            if term or trunc:
                obs, _ = env.reset()
            frames.append(np.asarray(obs)[..., -1])
        np.savez(cache, frames=np.stack(frames), acts=acts, rews=rews, ends=ends)
    z = np.load(cache)
    frames, acts, rews, ends = z["frames"], z["acts"], z["rews"], z["ends"]
    eps, start = [], 0
    for i in np.flatnonzero(ends).tolist() + [len(acts) - 1]:
        t = i + 1 - start
        if t >= 2:
            disc = np.ones(t, np.float32)
            disc[-1] = 0.0 if ends[i] == 2 else 1.0
            r = np.asarray(rews[start : i + 1], np.float32)
            eps.append(
                {
                    "observations": frames[start : i + 1],
                    "actions": np.asarray(acts[start : i + 1], np.int64),
                    "unclipped_rewards": r,
                    "clipped_rewards": np.clip(r, -1, 1),
                    "discounts": disc,
                }
            )
        start = i + 1
    return eps


def _png(frame: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(frame).save(buf, "PNG")
    return buf.getvalue()


def write_shard(path: Path, eps: list[dict], steps: int, offset: int, checkpoint: int) -> int:
    """An ``atari_episodes_ordered`` shard of about ``steps`` steps of ``eps`` (taken in turn
    from ``offset``); returns its steps."""
    path.parent.mkdir(parents=True, exist_ok=True)
    n, k = 0, offset
    with RecordWriter(path, compression="gzip") as w:
        while n < steps:
            e = eps[k % len(eps)]
            feats = {
                "observations": [_png(f) for f in e["observations"]],
                "actions": e["actions"],
                "unclipped_rewards": e["unclipped_rewards"],
                "clipped_rewards": e["clipped_rewards"],
                "discounts": e["discounts"],
                "checkpoint_idx": np.asarray([checkpoint], np.int64),
                "episode_idx": np.asarray([k], np.int64),
                "episode_return": np.asarray([e["unclipped_rewards"].sum()], np.float32),
                "clipped_episode_return": np.asarray([e["clipped_rewards"].sum()], np.float32),
            }
            w.write(ex.encode_example(feats))
            n += len(e["actions"])
            k += 1
    return n


def make_shards(work: Path, game: str, count: int, steps: int, pool: int) -> list[str]:
    eps = real_episodes(game, pool, work)
    folder = work / "bucket" / "atari_episodes_ordered" / game
    paths = []
    for i in range(count):
        p = folder / f"run_1-{i:05d}-of-{count:05d}"
        if not p.exists():
            write_shard(p, eps, steps, offset=7 * i, checkpoint=i)
        paths.append(str(p))
    return paths


def _same(a: Path, b: Path) -> bool:
    fa = sorted(str(p.relative_to(a)) for p in a.rglob("*") if p.is_file())
    fb = sorted(str(p.relative_to(b)) for p in b.rglob("*") if p.is_file())
    return fa == fb and all((a / r).read_bytes() == (b / r).read_bytes() for r in fa)


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


# --- shards: one job per core ----------------------------------------------------------------


def _one_shard(path: str, out: str, task: str, q) -> None:
    """In a fresh process: one shard job (its peak RSS is this process's)."""
    import rlu.codecs.png as png
    import rlu.data.release.families  # noqa: F401 (the imports' memory is not the job's)

    png._pil()
    base = rss_mb()
    t0 = time.perf_counter()
    job = DatasetJob(task, "atari_episodes_ordered", out, (path,), "run_1")
    convert_release([job], Backend("local", 1))
    q.put((time.perf_counter() - t0, peak_mb(), base))


def bench_shards(args, work: Path) -> None:
    paths = make_shards(work, args.game, args.shards, args.shard_steps, args.pool)
    size = sum(os.path.getsize(p) for p in paths)
    print(
        f"{args.shards} release-format shards of ~{args.shard_steps:,} steps of real {args.game}"
        f" frames: {size / 1e6:.1f} MB ({size / args.shards / args.shard_steps:.0f} B/step)"
    )
    ctx = mp.get_context("spawn")
    rates = []
    for i, p in enumerate(paths):
        q = ctx.Queue()
        out = work / f"one{i}"
        proc = ctx.Process(target=_one_shard, args=(p, str(out), f"atari/{args.game}", q))
        proc.start()
        seconds, peak, base = q.get()
        proc.join()
        steps = json.loads((out / "manifest.json").read_text())["counts"]["steps"]
        rates.append(steps / seconds)
        print(
            f"  shard {i}: {steps:,} steps in {seconds:.1f} s = {steps / seconds:,.0f} steps/s "
            f"on one core (download none, decode + deflate + part + assembly), peak RSS "
            f"{peak:.0f} MB ({base:.0f} MB before the job: Python, numpy, rlu, Pillow); {load()}"
        )
        shutil.rmtree(out)
    rate = float(np.median(rates))
    # the parts path against the direct one, and the assembly alone
    t0 = time.perf_counter()
    task = f"atari/{args.game}"
    convert(paths, "atari_episodes_ordered", task, work / "direct", workers=1, run=1)
    direct = time.perf_counter() - t0
    job = DatasetJob(task, "atari_episodes_ordered", str(work / "job"), tuple(paths))
    report = convert_release([job], Backend("local", 1))
    same = _same(work / "direct", work / "job")
    ds_bytes = _size(work / "job")
    steps = report.datasets[0].steps
    print(
        f"  all {args.shards}: convert() {direct:.1f} s, as shard jobs {report.seconds:.1f} s "
        f"(shards {report.shard_seconds:.1f} s + assembly {report.assemble_seconds:.2f} s = "
        f"{ds_bytes / 1e6 / max(report.assemble_seconds, 1e-9):.0f} MB/s); same bytes: {same}"
    )
    per_step = ds_bytes / steps
    run_hours = RUN_STEPS / rate / 3600
    print(
        f"  a run ({RUN_STEPS:,} steps, {RUN_STEPS // SHARD_STEPS} shards of {SHARD_STEPS:,}), "
        f"extrapolated from the median {rate:,.0f} steps/s per core: {run_hours:.1f} core-hours "
        f"({SHARD_STEPS / rate / 60:.1f} min per shard); converted {per_step * RUN_STEPS / 1e9:.1f}"
        f" GB ({per_step:.0f} B/step); assembly of the run at the measured rate: "
        f"{per_step * RUN_STEPS / (ds_bytes / max(report.assemble_seconds, 1e-9)) / 60:.1f} min"
    )
    shutil.rmtree(work / "direct")
    shutil.rmtree(work / "job")


# --- a Ray cluster on 127.0.0.1 ---------------------------------------------------------------


def _cluster_run(paths, task: str, out: Path, nodes: int, remove_after: int | None = None) -> dict:
    import ray

    from tests.release.ray_cluster import loopback_cluster

    with loopback_cluster([1] * nodes) as (cluster, workers):
        ray.init(address=cluster.address, log_to_driver=False)
        job = DatasetJob(task, "atari_episodes_ordered", str(out), tuple(paths), "run_1")
        seen: dict = {}
        if remove_after is not None:
            victim = workers[-1]

            def watch() -> None:  # remove a node once `remove_after` parts exist
                folder = parts_folder(out)
                while True:
                    done = [p for p in folder.glob("0*") if (p / "manifest.json").is_file()]
                    if len(done) >= remove_after:
                        break
                    time.sleep(0.05)
                inflight = [p.name for p in folder.glob(".*.partial")]
                cluster.remove_node(victim, allow_graceful=False)
                seen.update(victim=victim.node_id, at=len(done), inflight=inflight)

            threading.Thread(target=watch, daemon=True).start()
        t0 = time.perf_counter()
        report = convert_release([job], Backend("ray", address=cluster.address))
        wall = time.perf_counter() - t0
        ray.shutdown()
    return {"report": report, "wall": wall, **seen}


def bench_ray(args, work: Path) -> None:
    paths = make_shards(work, args.game, args.shards, args.shard_steps, args.pool)
    t0 = time.perf_counter()
    task = f"atari/{args.game}"
    convert(paths, "atari_episodes_ordered", task, work / "local", workers=1, run=1)
    local = time.perf_counter() - t0
    print(
        f"{args.shards} shards of ~{args.shard_steps:,} real {args.game} steps; local convert(), "
        f"1 process: {local:.1f} s = {args.shards / local:.3f} shards/s; {load()}"
    )
    for n in args.nodes:
        out = work / f"ray{n}"
        got = _cluster_run(paths, task, out, n)
        r = got["report"]
        per = ", ".join(
            f"{v['shards']:.0f} ({v['shards'] / r.shard_seconds:.3f}/s)" for v in r.nodes.values()
        )
        print(
            f"  {n} node(s) x 1 CPU: {r.shard_seconds:.1f} s of shard jobs = "
            f"{r.shards / r.shard_seconds:.3f} shards/s "
            f"({r.datasets[0].steps / r.shard_seconds:,.0f} steps/s); per node: {per}; assembly "
            f"{r.assemble_seconds:.2f} s; same bytes as local: {_same(work / 'local', out)}; "
            f"{load()}"
        )
        shutil.rmtree(out)
    out = work / "ray_loss"
    got = _cluster_run(paths, task, out, 2, remove_after=args.remove_after)
    r = got["report"]
    print(
        f"  2 nodes, the second removed once {got['at']} parts were done (in flight then: "
        f"{got['inflight']}): {r.shards} shards, per node "
        f"{ {k[:8]: int(v['shards']) for k, v in r.nodes.items()} }, removed node "
        f"{got['victim'][:8]} returned {int(r.nodes.get(got['victim'], {}).get('shards', 0))};"
        f" {r.shard_seconds:.1f} s; same bytes as local: {_same(work / 'local', out)}"
    )
    shutil.rmtree(out)
    shutil.rmtree(work / "local")


# --- a full-size run out of core -------------------------------------------------------------


def bench_ooc(args, work: Path) -> None:
    from rlu.data import TransitionView, open_dataset
    from rlu.data.store import DatasetWriter
    from rlu.data.views import Sampler

    paths = make_shards(work, args.game, 1, args.block_steps, args.pool)
    block = work / "block"
    if not block.exists():
        convert(paths, "atari_episodes_ordered", f"atari/{args.game}", block, workers=1, run=1)
    b = open_dataset(block)
    copies = -(-args.steps // b.num_steps)
    print(
        f"out of core: {copies:,} copies of one converted shard of {b.num_steps:,} real "
        f"{args.game} steps ({b.num_segments} episodes), appended as a cluster job assembles "
        f"parts (DatasetWriter.append_dataset)"
    )
    big = work / "run"
    t0 = time.perf_counter()
    with DatasetWriter(big, b.schema, provenance={"source": "bench-ooc"}) as w:
        for _ in range(copies):
            w.append_dataset(block)
    write = time.perf_counter() - t0
    size = _size(big)
    frames = (big / "steps" / "observation.zlib").stat().st_size
    print(
        f"  wrote {size / 1e9:.2f} GB in {write:.0f} s ({size / 1e6 / write:.0f} MB/s), writer "
        f"peak RSS {peak_mb():.0f} MB; frames {frames / 1e9:.2f} GB; {load()}"
    )
    del b
    t0 = time.perf_counter()
    ds = open_dataset(big)
    view = TransitionView(ds)
    opened = time.perf_counter() - t0
    Sampler(view, 32, seed=0).sample()
    first = time.perf_counter() - t0
    print(
        f"  open_dataset + TransitionView: {opened:.2f} s for {ds.num_steps:,} steps, "
        f"{ds.num_segments:,} episodes; with the first batch (the frame offsets mapped and "
        f"checked): {first:.2f} s; {rss_parts()}"
    )
    for batch in (32, 256):
        s = Sampler(view, batch, seed=batch)
        x = s.sample()
        assert np.asarray(x.observation).shape == (batch, 84, 84, 4)
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < args.seconds:
            s.sample()
            n += 1
        dt = time.perf_counter() - t0
        print(
            f"  stacked-frame SARSA batch {batch}: {n * batch / dt:,.0f} transitions/s, "
            f"{rss_parts()}"
        )
    print(f"  peak RSS over the run: {peak_mb():.0f} MB")
    nsteps, nframes = ds.num_steps, ds.num_frames
    del view, ds, s, x
    shutil.rmtree(big)
    other = (size - frames) / nsteps  # bytes per step besides the frames' streams
    print(
        f"  per run of {RUN_STEPS:,} steps: frames raw {RUN_STEPS * 84 * 84 / 1e9:.0f} GB, zlib "
        f"{frames / nframes * RUN_STEPS / 1e9:.1f} GB ({frames / nframes:.0f} B/frame, this "
        f"game); other columns {other * RUN_STEPS / 1e9:.2f} GB ({other:.1f} B/step, the "
        f"frames' zlib offsets included)"
    )


def frame_sizes(args, work: Path) -> None:
    """Per-frame zlib (level 1, the store's) and PNG sizes of real frames of several games."""
    print("per frame, real frames under a random policy: zlib level 1 (the store) / PNG (Pillow)")
    for game in args.games:
        eps = real_episodes(game, args.pool, work)
        f = np.concatenate([e["observations"] for e in eps])[::7]
        z = float(np.mean([len(zlib.compress(x.tobytes(), 1)) for x in f]))
        p = float(np.mean([len(_png(x)) for x in f]))
        print(
            f"  {game:14s} zlib {z:6.0f} B  PNG {p:6.0f} B  -> a run's frames: zlib "
            f"{z * RUN_STEPS / 1e9:5.1f} GB, PNG {p * RUN_STEPS / 1e9:5.1f} GB"
        )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=["shards", "ray", "ooc", "frames"])
    ap.add_argument("--game", default="Pong")
    ap.add_argument(
        "--games",
        nargs="+",
        default=["Pong", "Breakout", "Seaquest", "Asterix", "SpaceInvaders", "MsPacman"],
    )
    ap.add_argument("--pool", type=int, default=20_000, help="env steps of real frames")
    ap.add_argument("--shards", type=int, default=4)
    ap.add_argument("--shard-steps", type=int, default=20_000)
    ap.add_argument("--nodes", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--remove-after", type=int, default=2)
    ap.add_argument("--steps", type=int, default=RUN_STEPS)
    ap.add_argument("--block-steps", type=int, default=30_000)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--keep", action="store_true")
    args = ap.parse_args()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="rlu_cluster_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        {"shards": bench_shards, "ray": bench_ray, "ooc": bench_ooc, "frames": frame_sizes}[
            args.what
        ](args, work)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
