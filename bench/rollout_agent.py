"""Evaluation of a trained D4PG policy: ``rlu evaluate``'s path
(``rlu.training.restore.evaluate_run``: lockstep envs, one batched ``agent.act`` per step) vs a
plain loop over a TorchScript copy of the same policy network, one env, one torch thread (the loop
issue 19 timed: 30 episodes in 15 s where ``rlu evaluate`` ran 10 in 61 s on a loaded 2-core
machine).

    .venv/bin/python bench/rollout_agent.py [--episodes 8] [--threads 1] [--preset small]

The run is a D4PG trained for a few steps on the bundled cartpole_swingup data (the speed of a
forward pass does not depend on the weights; episodes are 1000 steps whatever the policy). Both
sides play the same episode seeds (``rlu.evaluation.rollout.episode_seed``), so their returns
must agree; the ratio printed is episodes/s of rlu over the TorchScript loop.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("MUJOCO_GL", "egl")

import torch  # noqa: E402

from rlu.evaluation.rollout import episode_seed  # noqa: E402
from rlu.training.config import RunSettings  # noqa: E402
from rlu.training.restore import evaluate_run, load_agent  # noqa: E402
from rlu.training.train import TrainConfig, train  # noqa: E402

TASK = "control_suite/cartpole_swingup"


def make_run(root: Path, preset: str) -> Path:
    from rlu.data.bundled import bundled_dataset

    run = RunSettings(preset=preset, steps=5, eval_every=-1, checkpoint_every=5)
    cfg = TrainConfig(task=TASK, agent="d4pg", dataset=str(bundled_dataset()), run=run)
    train(cfg, root / "d4pg", progress=False)
    return root / "d4pg"


def traced_policy(run: Path):
    """The run's policy network as TorchScript (frozen), fed the observation dict as the agent's
    act feeds it; D4PG's actions are already in [-1, 1], the env's action range."""
    agent, resolved = load_agent(run)
    keys = sorted(resolved["observation_spec"])
    shapes = {k: resolved["observation_spec"][k]["shape"] for k in keys}
    example = {k: torch.zeros((1, *shapes[k])) for k in keys}
    with torch.inference_mode():
        script = torch.jit.trace(agent.policy.eval(), (example,), strict=False)
    return torch.jit.freeze(script.eval()), keys


def torchscript_loop(script, keys, episodes: int, seed: int) -> list[float]:
    import rlu

    env, returns = rlu.make_env(TASK), []
    for i in range(episodes):
        obs, _ = env.reset(seed=episode_seed(seed, i))
        done, total = False, 0.0
        while not done:
            with torch.inference_mode():
                x = {k: torch.from_numpy(obs[k][None]) for k in keys}
                a = script(x).numpy()[0]
            obs, r, term, trunc, _ = env.step(a)
            total += float(r)
            done = term or trunc
        returns.append(total)
    env.close()
    return returns


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--envs", type=int, default=4)
    ap.add_argument("--threads", type=int, default=1, help="torch threads on rlu's side")
    ap.add_argument("--preset", default="small", choices=["small", "paper"])
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        torch.set_num_threads(1)
        run = make_run(Path(tmp), args.preset)
        script, keys = traced_policy(run)
        n = args.episodes
        torchscript_loop(script, keys, 1, seed=99)  # warm-up: TorchScript's first calls
        t_ts, ret_ts = timed(lambda: torchscript_loop(script, keys, n, seed=0))
        torch.set_num_threads(args.threads)
        t_rlu, res = timed(lambda: evaluate_run(run, episodes=n, seed=0, num_envs=args.envs))
    assert np.allclose(res.returns, ret_ts, rtol=1e-4, atol=1e-3), (res.returns, ret_ts)
    print(f"{n} episodes of 1000 steps, D4PG {args.preset} preset, {TASK}")
    print(f"  TorchScript loop, 1 env, 1 thread  {n / t_ts:7.2f} episodes/s")
    print(f"  rlu evaluate, {args.envs} envs, {args.threads} thread(s)  {n / t_rlu:7.2f} episodes/s"
          f"   rlu / TorchScript = {t_ts / t_rlu:.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
