"""Uniform SARSA batches from rlu's memory-mapped store vs peers, on the same data in one run.

    .venv-bench/bin/python bench/sampling.py        # peers: in-RAM numpy, d3rlpy, Minari, D4RL loop
    .venv-bench/bin/python bench/sampling.py --ooc  # the out-of-core Atari check (> 4 GB) alone,
                                                    # in its own process so peak RSS is its own

The bench environment needs d3rlpy, minari and psutil besides rlu (see bench/README.md); a peer
that is not installed is reported as skipped. Data: a synthetic dataset of 1M steps (observation
dim 17, action dim 6, 1000-step episodes), written once with rlu's writer and handed to every
peer as the same arrays. Figures are transitions per second over ``--seconds`` of sampling.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rlu.data import DatasetWriter, Schema, TransitionView, make_episode, open_dataset  # noqa: E402
from rlu.data.views import Sampler  # noqa: E402
from rlu.types import ArraySpec, BoundedSpec, DiscreteSpec  # noqa: E402


def rate(fn, batch: int, seconds: float) -> float:
    fn()  # warm-up (page faults, lazy imports)
    n, t0 = 0, time.perf_counter()
    while (dt := time.perf_counter() - t0) < seconds:
        fn()
        n += 1
    return n * batch / dt


def rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def build(path: Path, steps: int, ep_len: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    n_ep = steps // ep_len
    schema = Schema(ArraySpec((17,), "float32"), BoundedSpec((6,), "float32"))
    flat = {k: [] for k in ("obs", "act", "rew", "term", "timeout")}
    with DatasetWriter(path, schema, {"source": "bench"}) as w:
        for _ in range(n_ep):
            obs = rng.standard_normal((ep_len + 1, 17), dtype=np.float32)
            act = rng.uniform(-1, 1, (ep_len, 6)).astype(np.float32)
            rew = rng.random(ep_len, dtype=np.float32)
            w.append(make_episode(obs, act, rew, terminal=False))
            flat["obs"].append(obs)
            flat["act"].append(act)
            flat["rew"].append(rew)
    return {k: np.concatenate(v) for k, v in flat.items() if v} | {"n_ep": n_ep, "ep_len": ep_len}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=1_000_000)
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--ooc", action="store_true", help="run only the out-of-core Atari check")
    ap.add_argument("--ooc-gb", type=float, default=4.2)
    ap.add_argument("--workdir", default=None)
    args = ap.parse_args()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="rlu_bench_"))
    B, S = args.batch, args.seconds
    if args.ooc:
        out_of_core(work, args.ooc_gb, S)
        shutil.rmtree(work, ignore_errors=True)
        return
    print(f"data: {args.steps:,} steps, obs 17, action 6, 1000-step episodes; batch {B}")
    t0 = time.perf_counter()
    raw = build(work / "ds", args.steps, 1000, 0)
    print(f"wrote rlu dataset in {time.perf_counter() - t0:.1f}s")

    ds = open_dataset(work / "ds")
    sampler = Sampler(TransitionView(ds), B, seed=0)
    results: dict[str, float] = {}
    results["rlu (memmap store)"] = rate(sampler.sample, B, S)

    # (a) in-RAM numpy fancy indexing over transition indices: the practical bound
    n_ep, L = raw["n_ep"], raw["ep_len"]
    obs, act, rew = raw["obs"], raw["act"], raw["rew"]
    steps_per_ep = L + 1
    act_full = np.concatenate([act.reshape(n_ep, L, 6), np.zeros((n_ep, 1, 6), np.float32)], 1)
    act_full = act_full.reshape(-1, 6)
    rew_full = np.concatenate([rew.reshape(n_ep, L), np.zeros((n_ep, 1), np.float32)], 1).ravel()
    valid = (np.arange(n_ep)[:, None] * steps_per_ep + np.arange(L)).ravel()
    rng = np.random.default_rng(0)

    disc_full = np.ones_like(rew_full)

    def numpy_batch():  # the same tuple: (s, a, r, discount, s', a')
        i = valid[rng.integers(0, len(valid), B)]
        return obs[i], act_full[i], rew_full[i], disc_full[i], obs[i + 1], act_full[i + 1]

    results["(a) numpy in RAM"] = rate(numpy_batch, B, S)

    # the same flat arrays in D4RL / d3rlpy layout (one row per transition)
    o_t = obs.reshape(n_ep, steps_per_ep, 17)[:, :-1].reshape(-1, 17)
    o_tp1 = obs.reshape(n_ep, steps_per_ep, 17)[:, 1:].reshape(-1, 17)
    timeouts = np.zeros(n_ep * L, bool)
    timeouts[L - 1 :: L] = True
    terminals = np.zeros(n_ep * L, bool)

    # (b) d3rlpy
    try:
        import d3rlpy

        d3 = d3rlpy.dataset.MDPDataset(
            observations=o_t,
            actions=act,
            rewards=rew[:, None],
            terminals=terminals,
            timeouts=timeouts,
        )
        results["(b) d3rlpy sample_transition_batch"] = rate(
            lambda: d3.sample_transition_batch(B), B, S
        )
    except ImportError as e:
        print(f"d3rlpy not usable ({e}): skipped")

    # (c) Minari: exact uniform transitions through its episode API, and its episode sampling
    try:
        import gymnasium as gym
        import minari
        from minari.data_collector import EpisodeBuffer

        os.environ["MINARI_DATASETS_PATH"] = str(work / "minari")
        episodes = []
        for e in range(n_ep):
            sl = slice(e * steps_per_ep, (e + 1) * steps_per_ep)
            episodes.append(
                EpisodeBuffer(
                    id=e,
                    observations=obs[sl],
                    actions=act[e * L : (e + 1) * L],
                    rewards=rew[e * L : (e + 1) * L],
                    terminations=np.zeros(L, bool),
                    truncations=np.r_[np.zeros(L - 1, bool), True],
                )
            )
        mds = minari.create_dataset_from_buffers(
            "bench/sampling-v0",
            episodes,
            observation_space=gym.spaces.Box(-np.inf, np.inf, (17,), np.float32),
            action_space=gym.spaces.Box(-1, 1, (6,), np.float32),
            algorithm_name="synthetic",
        )
        mrng = np.random.default_rng(0)

        def minari_uniform():
            tid = mrng.integers(0, n_ep * L, B)
            ep, t = tid // L, tid % L
            uniq, inv = np.unique(ep, return_inverse=True)
            eps = list(mds.iterate_episodes(episode_indices=uniq.tolist()))
            o = np.stack([eps[j].observations[k] for j, k in zip(inv, t, strict=True)])
            o2 = np.stack([eps[j].observations[k + 1] for j, k in zip(inv, t, strict=True)])
            return o, o2

        results["(c) Minari uniform transitions"] = rate(minari_uniform, B, S)
        eps_per_call = max(1, B // L)
        results["(c) Minari sample_episodes (steps/s)"] = rate(
            lambda: mds.sample_episodes(eps_per_call), eps_per_call * L, S
        )
    except ImportError as e:
        print(f"minari not usable ({e}): skipped")

    # (d) D4RL-style Python loop building each transition one at a time
    drng = np.random.default_rng(0)

    def d4rl_loop():
        out = {k: [] for k in ("o", "a", "r", "o2", "d")}
        for i in drng.integers(0, len(o_t), B).tolist():
            out["o"].append(o_t[i])
            out["a"].append(act[i])
            out["r"].append(rew[i])
            out["o2"].append(o_tp1[i])
            out["d"].append(bool(terminals[i]))
        return {k: np.array(v) for k, v in out.items()}

    results["(d) D4RL-style Python loop"] = rate(d4rl_loop, B, S)

    base = results["rlu (memmap store)"]
    print(f"\n{'method':42s} {'transitions/s':>14s} {'rlu / method':>13s}")
    for k, v in results.items():
        print(f"{k:42s} {v:14,.0f} {base / v:12.2f}x")
    print(
        f"\nrlu reaches {100 * base / results['(a) numpy in RAM']:.0f}% of in-RAM numpy "
        "(target >= 50%)"
    )
    shutil.rmtree(work, ignore_errors=True)


def out_of_core(work: Path, gb: float, seconds: float) -> None:
    """Stacked 84x84 frames from a dataset larger than 4 GB: resident memory stays bounded."""
    frames = int(gb * 2**30 / (84 * 84))
    ep_len = 2000
    n_ep = frames // (ep_len + 4) + 1
    schema = Schema(ArraySpec((84, 84), "uint8"), DiscreteSpec((), "int64", 6), frame_stack=4)
    rng = np.random.default_rng(1)
    block = rng.integers(0, 256, (ep_len + 1, 84, 84), dtype=np.uint8)
    t0 = time.perf_counter()
    with DatasetWriter(work / "atari", schema, {"source": "bench-ooc"}) as w:
        for e in range(n_ep):
            w.append(
                make_episode(
                    np.roll(block, e, axis=0), np.zeros(ep_len, np.int64), np.zeros(ep_len), True
                )
            )
    size = sum(f.stat().st_size for f in (work / "atari").rglob("*") if f.is_file())
    print(
        f"\nout-of-core: wrote {size / 2**30:.2f} GiB ({n_ep} episodes) in "
        f"{time.perf_counter() - t0:.0f}s"
    )
    ds = open_dataset(work / "atari")
    for batch in (32, 256):
        s = Sampler(TransitionView(ds), batch, seed=0)
        r = rate(s.sample, batch, seconds)
        print(
            f"  stacked-frame SARSA batch {batch:4d}: {r:10,.0f} transitions/s, "
            f"RSS now {rss_mb():.0f} MB"
        )
    # cover the whole file once more, then report the peak
    s = Sampler(TransitionView(ds), 256, seed=1)
    for _ in range(3 * len(s.view) // 256 // 20):
        s.sample()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"  peak resident memory over the run: {peak:.0f} MB (target < 1536 MB; "
        f"dataset {size / 2**20:.0f} MB)"
    )


if __name__ == "__main__":
    main()
