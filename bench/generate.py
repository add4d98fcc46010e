"""Recording overhead: env steps/s of the raw env loop against the same loop recording episodes.

    MUJOCO_GL=egl .venv/bin/python bench/generate.py            # cartpole swingup + Pong
    MUJOCO_GL=egl .venv/bin/python bench/generate.py --quick    # fewer steps

The same pre-drawn random actions drive both loops through whole episodes (reset with the same
seeds). "record" adds ``EpisodeRecorder.step`` on every step; "record+store" also appends every
finished episode to a ``DatasetWriter`` in a temporary directory and finalises it (fsync, hashes,
manifest). Rounds alternate and the best round of each counts (the machine is shared). The
ratio raw / recorded is the slowdown recording costs (1.00 = free). Acting and learning are left
out: they cost the same with and without recording.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
os.environ.setdefault("MUJOCO_GL", "egl")

from rlu.data import DatasetWriter  # noqa: E402
from rlu.envs import make_env  # noqa: E402
from rlu.generate.recorder import EpisodeRecorder, schema_for  # noqa: E402
from rlu.tasks import get_task  # noqa: E402


def _actions(env, n: int) -> list:
    rng = np.random.default_rng(0)
    space = env.action_space
    if hasattr(space, "n"):
        return [np.int64(x) for x in rng.integers(space.n, size=n)]
    return list(rng.uniform(-1, 1, (n, *space.shape)).astype(np.float32))


def loop(env, actions, recorder=None, writer=None) -> float:
    episode = 0
    obs, _ = env.reset(seed=episode)
    if recorder is not None:
        recorder.begin(obs)
    t0 = time.perf_counter()
    for a in actions:
        obs, r, term, trunc, info = env.step(a)
        if recorder is not None:
            seg = recorder.step(a, r, obs, term, trunc, info, {"episode_index": episode})
            if seg is not None and writer is not None:
                writer.append(seg)
        if term or trunc:
            episode += 1
            obs, _ = env.reset(seed=episode)
            if recorder is not None:
                recorder.begin(obs)
    if writer is not None:
        writer.close()
    return len(actions) / (time.perf_counter() - t0)


def bench(task_id: str, steps: int, rounds: int, settings: dict) -> None:
    task = get_task(task_id)
    env = make_env(task_id, seed=0, **settings)
    actions = _actions(env, steps)
    max_steps = settings.get("max_episode_steps", task.episode_length)
    best = {"raw": 0.0, "record": 0.0, "record+store": 0.0}
    rec = EpisodeRecorder(task, max_steps)

    def once(kind: str) -> float:
        if kind == "raw":
            return loop(env, actions)
        if kind == "record":
            return loop(env, actions, rec)
        with tempfile.TemporaryDirectory() as d:
            return loop(env, actions, rec, DatasetWriter(os.path.join(d, "ds"), schema_for(task)))

    for i in range(rounds):  # the order flips every round: no loop always runs first
        for kind in list(best)[:: 1 if i % 2 == 0 else -1]:
            best[kind] = max(best[kind], once(kind))
    raw = best["raw"]
    print(f"{task_id}: {steps} steps, best of {rounds} rounds")
    for k, v in best.items():
        print(f"  {k:<13} {v:9.0f} steps/s   raw/{k} = {raw / v:5.3f}")
    # the recorder's own cost per step, without the env's noise around it
    obs, _ = env.reset(seed=0)
    obs2, r, term, trunc, info = env.step(actions[0])
    n = min(max_steps - 1, 1000)
    rec.begin(obs)
    t0 = time.perf_counter()
    for _ in range(n):
        rec.step(actions[0], r, obs2, False, False, info, None)
    per = (time.perf_counter() - t0) / n
    print(f"  recorder.step alone: {per * 1e6:.1f} us/step = {per * raw:.1%} of a raw env step")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    rounds = 2 if args.quick else 5
    bench("control_suite/cartpole_swingup", 2_000 if args.quick else 10_000, rounds, {})
    try:
        bench("atari/Pong", 1_000 if args.quick else 5_000, rounds, {"max_episode_steps": 1_000})
    except ImportError as e:
        print(f"atari/Pong skipped: {e}")


if __name__ == "__main__":
    main()
