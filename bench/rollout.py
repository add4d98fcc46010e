"""Evaluation rollouts: rlu's lockstep envs (one batched policy call per step) vs peers, on the
same env, policy and episode count in one run.

    .venv/bin/python bench/rollout.py [--episodes 16] [--envs 8] [--hidden 256]

Peers: a one-env-at-a-time loop with a policy call per step (the loop most offline-RL libraries
use to evaluate, e.g. d3rlpy's ``evaluate_qlearning_with_environment``), and gymnasium's own
``SyncVectorEnv`` stepping the same number of envs. Env: Pendulum-v1 with dict observations and
200-step episodes (tests/train/pendulum.py); policy: a torch MLP on the CPU. A trained agent's
policy against a TorchScript loop: ``bench/rollout_agent.py``. Figures are episodes
per second; one thread for torch so the comparison is the loop, not BLAS threading.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gymnasium as gym  # noqa: E402
import torch  # noqa: E402

from rlu.evaluation.rollout import episode_seed, evaluate  # noqa: E402
from tests.train.pendulum import make_env  # noqa: E402


def make_policy(hidden: int):
    torch.manual_seed(0)
    net = torch.nn.Sequential(
        torch.nn.Linear(3, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, hidden),
        torch.nn.ReLU(), torch.nn.Linear(hidden, 1), torch.nn.Tanh(),
    )  # fmt: skip

    def policy(obs, is_first=None, reward=None):
        x = np.concatenate([obs["orientation"], obs["velocity"]], axis=1)
        with torch.no_grad():
            return 2.0 * net(torch.from_numpy(x)).numpy()

    return policy


def _long_env():
    return make_env("test/pendulum", episode_steps=200)


def one_at_a_time(policy, episodes: int) -> list[float]:
    env, returns = _long_env(), []
    for i in range(episodes):
        obs, _ = env.reset(seed=episode_seed(0, i))
        done, total = False, 0.0
        while not done:
            batch = {k: v[None] for k, v in obs.items()}
            obs, r, term, trunc, _ = env.step(policy(batch)[0])
            total += float(r)
            done = term or trunc
        returns.append(total)
    return returns


def gym_sync_vector(policy, episodes: int, envs: int) -> list[float]:
    vec = gym.vector.SyncVectorEnv([_long_env for _ in range(envs)])
    obs, _ = vec.reset(seed=list(range(envs)))
    returns, running = [], np.zeros(envs)
    while len(returns) < episodes:
        obs, r, term, trunc, _ = vec.step(policy(obs))
        running += r
        for i in np.flatnonzero(term | trunc):
            returns.append(float(running[i]))
            running[i] = 0.0
        # gymnasium's next-step autoreset: the step after a done only resets that env
        if (term | trunc).any():
            obs, _, _, _, _ = vec.step(policy(obs))
    vec.close()
    return returns[:episodes]


def timed(fn) -> tuple[float, list[float]]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--episodes", type=int, default=16)
    ap.add_argument("--envs", type=int, default=8)
    ap.add_argument("--hidden", type=int, default=256)
    args = ap.parse_args()
    torch.set_num_threads(1)
    policy = make_policy(args.hidden)
    n = args.episodes
    # warm-up: torch's first calls, gymnasium's env registry and imports
    evaluate(policy, _long_env, 2, seed=0, num_envs=2)
    gym_sync_vector(policy, 2, 2)
    t_rlu, res = timed(lambda: evaluate(policy, _long_env, n, seed=0, num_envs=args.envs))
    t_one, ret_one = timed(lambda: one_at_a_time(policy, n))
    t_vec, _ = timed(lambda: gym_sync_vector(policy, n, args.envs))
    # same seeds -> same episodes as the one-env loop
    assert np.allclose(res.returns, ret_one, rtol=1e-5), "rlu and the one-env loop disagree"
    print(f"{n} episodes of 200 steps, MLP {args.hidden}x{args.hidden}, {args.envs} envs")
    print(f"  rlu evaluate (lockstep)   {n / t_rlu:8.2f} episodes/s")
    print(f"  one env at a time         {n / t_one:8.2f} episodes/s   rlu is {t_one / t_rlu:.2f}x")
    print(f"  gymnasium SyncVectorEnv   {n / t_vec:8.2f} episodes/s   rlu is {t_vec / t_rlu:.2f}x")


if __name__ == "__main__":
    main()
