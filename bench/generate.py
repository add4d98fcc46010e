"""Recording overhead: env steps/s of the raw env loop against the same loop recording episodes.

    MUJOCO_GL=egl .venv/bin/python bench/generate.py            # cartpole swingup + Pong
    MUJOCO_GL=egl .venv/bin/python bench/generate.py --quick    # fewer steps
    MUJOCO_GL=egl .venv/bin/python bench/generate.py --learner  # a behaviour run's CPU per step

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


def learner(task_id: str, rounds: int, updates: int) -> None:
    """``--learner``: where a laptop-scale behaviour run's CPU goes, one thread, as the run has
    it: D4PG updates of the small preset (batch 256) and of the laptop scale's settings
    (interleaved rounds, best of each), the act and the env step, and the per-env-step cost
    at each scale's updates per step."""
    import torch

    from rlu.agents import make_agent
    from rlu.generate.online import Replay
    from rlu.generate.scales import get_scale

    torch.set_num_threads(1)
    task = get_task(task_id)
    online = get_scale(task, "laptop").online
    env = make_env(task_id, seed=0)
    rec = EpisodeRecorder(task)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    rec.begin(obs)
    t0 = time.perf_counter()
    while True:
        a = rng.uniform(-1, 1, task.action_spec.shape).astype(np.float32)
        obs, r, term, trunc, info = env.step(a)
        seg = rec.step(a, r, obs, term, trunc, info, {})
        if seg is not None:
            break
    env_ms = (time.perf_counter() - t0) / (len(seg) - 1) * 1e3
    kinds = {"small preset": {}, "laptop": dict(online.agent_overrides)}
    agents, replays = {}, {}
    for k, over in kinds.items():
        agents[k] = make_agent("d4pg", task.observation_spec, task.action_spec, "small", 0, **over)
        replays[k] = Replay(task, 5_000, agents[k].batch_spec)
        replays[k].add(seg)
    best = dict.fromkeys(kinds, float("inf"))
    for i in range(rounds):
        for k in list(kinds)[:: 1 if i % 2 == 0 else -1]:
            agent, bs = agents[k], agents[k].config.batch_size
            batches = [replays[k].sample(rng, bs) for _ in range(updates)]
            t0 = time.perf_counter()
            for b in batches:
                agent.update(b)
            best[k] = min(best[k], (time.perf_counter() - t0) / updates * 1e3)
    ob = {k: v[None] for k, v in obs.items()}
    t0 = time.perf_counter()
    for _ in range(200):
        agents["laptop"].act(ob)
    act_ms = (time.perf_counter() - t0) / 200 * 1e3
    print(f"{task_id}: one thread, best of {rounds} rounds of {updates} updates")
    print(f"  env step {env_ms:.3f} ms, act {act_ms:.3f} ms")
    for k, every in (("small preset", 1), ("laptop", online.update_every)):
        bs = agents[k].config.batch_size
        per_step = env_ms + act_ms + best[k] / every
        print(
            f"  {k:<12} batch {bs}: update {best[k]:6.2f} ms; 1 update per {every} steps -> "
            f"{per_step:5.2f} ms per env step, {per_step:.1f} s per 1000-step episode"
        )
    print(f"  update time laptop / small preset = {best['laptop'] / best['small preset']:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--learner", action="store_true", help="a behaviour run's CPU per env step")
    args = ap.parse_args()
    if args.learner:
        learner("control_suite/walker_walk", 3 if args.quick else 5, 50 if args.quick else 200)
        return
    rounds = 2 if args.quick else 5
    bench("control_suite/cartpole_swingup", 2_000 if args.quick else 10_000, rounds, {})
    try:
        bench("atari/Pong", 1_000 if args.quick else 5_000, rounds, {"max_episode_steps": 1_000})
    except ImportError as e:
        print(f"atari/Pong skipped: {e}")


if __name__ == "__main__":
    main()
