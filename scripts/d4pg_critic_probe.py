"""What a trained D4PG critic says about the data's actions, its policy's and random ones.

    python scripts/d4pg_critic_probe.py RUN_DIR DATASET_DIR [--episodes 30]

RUN_DIR is an ``rlu train`` run (or one run of a sweep) of the ``d4pg`` agent; DATASET_DIR the
data it learned from. On steps 0, 10, ..., 490 of ``--episodes`` episodes drawn with seed 0 it
prints the mean of the critic's expected value for the data's action, the policy's action and a
uniform random action, next to the data's discounted return from that step (gamma 0.99; the
1,000-step cut-off weighs at most 0.99^500 = 0.7 % there). docs/fidelity.md has its figures
for the six control-suite tasks of the fidelity study.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from rlu.data import open_dataset
from rlu.training.restore import load_agent, read_run
from rlu.types import RluError, observation_spec_to_json


def discounted_returns(reward: np.ndarray, gamma: float) -> np.ndarray:
    out = np.zeros(len(reward) + 1)
    for t in range(len(reward) - 1, -1, -1):
        out[t] = reward[t] + gamma * out[t + 1]
    return out[:-1]


def measure(agent, ds, episodes: int) -> dict[str, np.ndarray]:
    """Per probed step: the data's discounted return ``mc``, the critic's expected value of the
    data's action, the policy's and a uniform random one, and the policy-data action gap."""
    rng = np.random.default_rng(0)
    rows = {"mc": [], "data": [], "policy": [], "random": [], "gap": []}
    for i in rng.choice(ds.num_segments, min(episodes, ds.num_segments), replace=False):
        seg = ds.segment(int(i))
        idx = np.arange(0, min(500, len(seg.reward)), 10)
        obs = {k: torch.as_tensor(v[idx]) for k, v in seg.observation.items()}
        action = agent.scaler.to_unit(torch.as_tensor(seg.action[idx]))
        rand = torch.as_tensor(rng.uniform(-1, 1, action.shape), dtype=torch.float32)
        with torch.no_grad():
            pi = agent.policy(obs)
            for name, a in (("data", action), ("policy", pi), ("random", rand)):
                rows[name].append(agent.critic.head.mean(agent.critic(obs, a)).numpy())
            rows["gap"].append((pi - action).abs().mean(-1).numpy())
        rewards = seg.reward.astype(np.float64)
        rows["mc"].append(discounted_returns(rewards, agent.config.gamma)[idx])
    return {k: np.concatenate(v) for k, v in rows.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("dataset")
    p.add_argument("--episodes", type=int, default=30)
    args = p.parse_args()
    if args.episodes < 1:
        raise SystemExit(f"error: --episodes {args.episodes}; use 1 or more")
    torch.set_num_threads(1)
    try:
        resolved, _, _ = read_run(args.run)
        if resolved["train"]["agent"] != "d4pg":
            raise RluError(
                f"{args.run} is a run of {resolved['train']['agent']!r}; this probe reads the "
                "categorical critic of a 'd4pg' run"
            )
        ds = open_dataset(args.dataset)
        agent, _ = load_agent(args.run)
    except RluError as e:
        raise SystemExit(f"error: {e}") from None
    if observation_spec_to_json(ds.schema.observation) != resolved["observation_spec"]:
        raise SystemExit(
            f"error: {args.dataset}'s observations are not those {args.run} trained on "
            f"({resolved['dataset']['path']}); pass the run's own dataset"
        )
    r = measure(agent, ds, args.episodes)
    returns = ds.episode_returns()
    p10, p50, p90 = np.percentile(returns, [10, 50, 90])
    print(f"data: {len(returns)} episodes, return mean {returns.mean():.1f} "
          f"(p10 {p10:.1f}, median {p50:.1f}, p90 {p90:.1f})")  # fmt: skip
    print(f"data's discounted return from the probed steps: {r['mc'].mean():.1f}")
    corr = np.corrcoef(r["data"], r["mc"])[0, 1]
    print(f"Q(s, data action):    {r['data'].mean():.1f} (correlation with it {corr:.2f})")
    print(f"Q(s, policy action):  {r['policy'].mean():.1f}")
    print(f"Q(s, random action):  {r['random'].mean():.1f}")
    print(f"|policy - data action| per dimension (actions in [-1, 1]): {r['gap'].mean():.2f}")


if __name__ == "__main__":
    main()
