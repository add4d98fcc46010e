"""Real Atari frames for bench/stream.py: random play through ``rlu.make_env`` written by rlu.

    PYTHONPATH=. .venv/bin/python bench/stream_data.py --out /tmp/rlu_stream --game MsPacman \\
        --parts 8 --steps 125000 --procs 2

Each part is ``--steps`` env steps of ``atari/GAME`` (Dopamine's preprocessing: 84x84 grey, frame
skip 4, sticky actions; the env's own episode ends) under a uniform random policy with its own
seed, written by :class:`rlu.data.DatasetWriter` with zlib frames and ``frame_stack`` 4, as
``rlu convert`` stores an Atari run. ``--procs`` parts are played at once (one process each).
Then ``run`` is assembled from the parts in order with ``DatasetWriter.append_dataset`` (a
cluster job's assembly: the same bytes), so the one-dataset and the mixture figures of
bench/stream.py read the same frames. Existing parts are kept (re-running resumes).
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def play(game: str, steps: int, seed: int, out: Path) -> tuple[str, int, float]:
    """``steps`` env steps of random play written to ``out``; (out, episodes, seconds)."""
    import rlu
    from rlu.data import DatasetWriter, Schema, make_episode
    from rlu.tasks import get_task

    schema = Schema.for_task(get_task(f"atari/{game}"), image_encoding="zlib")
    env = rlu.make_env(f"atari/{game}")
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    episodes = 0
    with DatasetWriter(
        out, schema, {"source": f"bench/stream_data.py random play, seed {seed}"}
    ) as w:
        obs, _ = env.reset(seed=seed)
        frames, acts, rews = [np.asarray(obs)[..., -1]], [], []
        for i in range(steps):
            a = int(rng.integers(env.action_space.n))
            obs, r, term, trunc, _ = env.step(a)
            frames.append(np.asarray(obs)[..., -1])
            acts.append(a)
            rews.append(r)
            if term or trunc or i == steps - 1:
                w.append(make_episode(np.stack(frames), np.asarray(acts, np.int64),
                                      np.asarray(rews, np.float32), bool(term)))  # fmt: skip
                episodes += 1
                obs, _ = env.reset()
                frames, acts, rews = [np.asarray(obs)[..., -1]], [], []
    return str(out), episodes, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--game", default="MsPacman")
    ap.add_argument("--parts", type=int, default=8)
    ap.add_argument("--steps", type=int, default=125_000, help="env steps per part")
    ap.add_argument("--procs", type=int, default=2)
    args = ap.parse_args()
    root = Path(args.out)
    root.mkdir(parents=True, exist_ok=True)
    todo = [(args.game, args.steps, 1000 + i, root / f"part{i}") for i in range(args.parts)
            if not (root / f"part{i}" / "manifest.json").exists()]  # fmt: skip
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(args.procs) as pool:
        for out, eps, secs in pool.starmap(play, todo):
            print(f"{out}: {args.steps:,} steps, {eps} episodes, {secs:.0f} s", flush=True)
    from rlu.data import DatasetWriter, open_dataset

    run = root / "run"
    if not (run / "manifest.json").exists():
        schema = open_dataset(root / "part0").schema
        with DatasetWriter(
            run, schema, {"source": f"bench/stream_data.py: {args.parts} parts"}
        ) as w:
            for i in range(args.parts):
                w.append_dataset(root / f"part{i}")
    ds = open_dataset(run)
    z = (run / "steps" / "observation.zlib").stat().st_size
    print(f"{run}: {ds.num_steps:,} steps, {ds.num_segments:,} episodes, {ds.num_frames:,} "
          f"frames, {z / ds.num_frames:,.0f} B a frame (zlib), {z / 1e9:.2f} GB")  # fmt: skip


if __name__ == "__main__":
    main()
