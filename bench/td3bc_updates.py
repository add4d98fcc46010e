"""rlu's TD3+BC against d3rlpy's TD3PlusBC update for update: the same initial weights (copied
from rlu's networks into d3rlpy's), the same batches (rlu's sampler, the observation keys
concatenated in sorted order for d3rlpy), the same observation statistics, the target
smoothing noise off (``policy_noise=0``: the two libraries draw it from different streams) and
d3rlpy's update counter started at 1, so that both step the actor on updates 2, 4, 6, ...
(d3rlpy's ``grad_step % 2 == 0`` counts from 0). Prints both libraries' losses and the largest
difference between their actions on 256 of the data's observations.

    .venv-bench/bin/python bench/td3bc_updates.py --updates 200

d3rlpy lives in the bench venv (bench/README.md). A difference that grows past float rounding
means the two updates are not the same maths.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from agents_continuous import d3rlpy_config  # noqa: E402
from new_agents import d3rlpy_buffer  # noqa: E402

from rlu.agents import make_agent  # noqa: E402
from rlu.data import open_dataset  # noqa: E402
from rlu.data.bundled import bundled_dataset  # noqa: E402
from rlu.data.statistics import dataset_statistics  # noqa: E402
from rlu.data.views import make_sampler  # noqa: E402


def linears(module: nn.Module) -> list[nn.Linear]:
    return [m for m in module.modules() if isinstance(m, nn.Linear)]


def copy_weights(source: nn.Module, dest: nn.Module) -> None:
    pairs = list(zip(linears(source), linears(dest), strict=True))
    with torch.no_grad():
        for a, b in pairs:
            b.weight.copy_(a.weight)
            b.bias.copy_(a.bias)


def joined(observation: dict) -> np.ndarray:
    return np.concatenate([observation[k] for k in sorted(observation)], -1).astype(np.float32)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--updates", type=int, default=200)
    p.add_argument("--every", type=int, default=50, help="print every N updates")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    try:
        import d3rlpy
        import structlog
        from d3rlpy.dataset import TransitionMiniBatch
    except ImportError:
        sys.exit("d3rlpy is not installed here: run this in the bench venv (bench/README.md)")
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))

    ds = open_dataset(bundled_dataset("control_suite/cartpole_swingup"))
    agent = make_agent("td3bc", ds.schema.observation, ds.schema.action, "small", policy_noise=0.0)
    stats = dataset_statistics(ds, agent.batch_spec.statistics)
    agent.set_statistics(stats)
    config = d3rlpy_config("td3bc", agent.config)
    config.observation_scaler = d3rlpy.preprocessing.StandardObservationScaler(
        mean=joined(stats.observation_mean), std=joined(stats.observation_std)
    )
    algo = config.create(device="cpu:0")
    algo.build_with_dataset(d3rlpy_buffer(ds, 1, False))
    m = algo.impl.modules
    for policy in (m.policy, m.targ_policy):
        copy_weights(agent.actor, policy)
    for i, q in enumerate((agent.critics.q1, agent.critics.q2)):
        copy_weights(q, m.q_funcs[i])
        copy_weights(q, m.targ_q_funcs[i])
    algo._grad_step = 1  # d3rlpy counts updates from 0; rlu's actor steps on updates 2, 4, ...

    keys = sorted(stats.observation_mean)
    probe = {k: np.array(ds.column(f"observation/{k}")[:256], np.float32) for k in keys}
    probe_t = {k: torch.from_numpy(v) for k, v in probe.items()}
    probe_d3 = config.observation_scaler.transform(torch.from_numpy(joined(probe)))
    sampler = make_sampler(ds, agent.batch_spec, seed=0)
    for step in range(1, args.updates + 1):
        b = sampler.sample()
        n = len(b.reward)
        mini = TransitionMiniBatch(
            observations=joined(b.observation), actions=b.action.astype(np.float32),
            rewards=b.reward.reshape(n, 1).astype(np.float32),
            next_observations=joined(b.next_observation),
            next_actions=b.next_action.astype(np.float32),
            terminals=(1.0 - b.discount).reshape(n, 1).astype(np.float32),
            intervals=np.ones((n, 1), np.float32), transitions=[],
        )  # fmt: skip
        ours, theirs = agent.update(b), algo.update(mini)
        if step % args.every == 0 or step <= 2:
            with torch.no_grad():
                diff = agent.actor(agent.normaliser(probe_t)) - m.policy(probe_d3).squashed_mu
            print(f"update {step}: rlu critic {ours['critic/loss']:.6f} actor "
                  f"{ours.get('actor/loss', float('nan')):.6f} | d3rlpy critic "
                  f"{theirs['critic_loss']:.6f} actor {theirs.get('actor_loss', float('nan')):.6f}"
                  f" | max |pi_rlu - pi_d3rlpy| {float(diff.abs().max()):.2e}")  # fmt: skip


if __name__ == "__main__":
    main()
