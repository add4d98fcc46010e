"""Updates per second of rlu's discrete agents vs d3rlpy and vs a minimal PyTorch loop (CPU).

    .venv-bench/bin/python bench/agents_discrete.py            # the paper's batch (256)
    .venv-bench/bin/python bench/agents_discrete.py --batch 32 --rounds 3

Contestants, all on the same fixed batch of random Atari frame stacks, the Nature CNN, Adam and
the same number of torch threads, timed in interleaved rounds (the median round counts, so a
burst of load from elsewhere on a shared machine hits every contestant alike; the order is
shuffled every round):

- rlu ``dqn`` (double-Q, the paper's preset) vs d3rlpy ``DoubleDQN`` (the same maths) and
  d3rlpy ``DQN`` (plain max target: one forward pass fewer per update);
- rlu ``bcq`` vs d3rlpy ``DiscreteBCQ`` (threshold 0.5). rlu's BCQ follows Fujimoto et al.:
  the imitation head has its own 512-unit layer; d3rlpy's shares the Q-function's 512 features,
  so rlu does more arithmetic per update here;
- a minimal PyTorch loop doing rlu's maths with no wrapper at all (tensors ready, straight-line
  code): the no-overhead bound for rlu's DQN and BCQ.

d3rlpy is timed on ``algo.update(batch)`` with the batch already built as the float32
``TransitionMiniBatch`` its samplers produce (its uint8 -> float32 copy is not counted), rlu on
``agent.update(transition)`` from uint8 numpy arrays. d3rlpy lives in its own venv
(``python -m venv .venv-bench; pip install torch==2.13.0 d3rlpy==2.8.1``) so the project's
environment stays free of it; without d3rlpy only the minimal-loop comparison runs.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rlu.agents import make_agent  # noqa: E402
from rlu.types import ArraySpec, DiscreteSpec, Transition  # noqa: E402

OBS = ArraySpec((84, 84, 4), "uint8")
NUM_ACTIONS = 6
LR, GAMMA, TARGET_PERIOD, EPS = 1e-4, 0.99, 2500, 1e-7


def make_batch(size: int, seed: int = 0) -> Transition:
    """Random frames laid out as rlu's views give them: (B, 84, 84, 4) views of frame-major
    (B, 4, 84, 84) memory (the store gathers whole frames, then moves the stack axis last)."""
    rng = np.random.default_rng(seed)

    def frames():
        return rng.integers(0, 256, (size, 4, 84, 84), dtype=np.uint8).transpose(0, 2, 3, 1)

    return Transition(
        observation=frames(),
        action=rng.integers(0, NUM_ACTIONS, size).astype(np.int64),
        reward=rng.uniform(-1, 1, size).astype(np.float32),
        discount=(rng.random(size) > 0.05).astype(np.float32),
        next_observation=frames(),
        next_action=rng.integers(0, NUM_ACTIONS, size).astype(np.int64),
    )


# ----------------------------------------------------------------------------- rlu


def rlu_step(name: str, batch: Transition):
    agent = make_agent(
        name,
        OBS,
        DiscreteSpec((), "int64", NUM_ACTIONS),
        "paper",
        learning_rate=LR,
        **{"atari.batch_size": len(batch.action)},
    )
    return lambda: agent.update(batch)


# ----------------------------------------------------------------------------- minimal loop


def nature_cnn() -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(4, 32, 8, 4), nn.ReLU(), nn.Conv2d(32, 64, 4, 2), nn.ReLU(),
        nn.Conv2d(64, 64, 3, 1), nn.ReLU(), nn.Flatten(),
    )  # fmt: skip


def head() -> nn.Sequential:
    return nn.Sequential(nn.Linear(3136, 512), nn.ReLU(), nn.Linear(512, NUM_ACTIONS))


def minimal_dqn_step(batch: Transition):
    """Double DQN with Huber loss, the same forward passes as rlu, no wrapper."""
    torso, q_head = nature_cnn(), head()
    net = nn.Sequential(torso, q_head)
    target = nn.Sequential(nature_cnn(), head())
    target.load_state_dict(net.state_dict())
    opt = torch.optim.Adam(net.parameters(), lr=LR, eps=EPS)
    o = torch.from_numpy(batch.observation)
    o2 = torch.from_numpy(batch.next_observation)
    a, r, d = (torch.from_numpy(x) for x in (batch.action, batch.reward, batch.discount))
    steps = [0]

    def frames(x):
        x = x.permute(0, 3, 1, 2).contiguous(memory_format=torch.channels_last)
        return x.float().mul_(1 / 255)

    def step():
        q = net(frames(o)).gather(1, a[:, None]).squeeze(1)
        with torch.no_grad():
            x2 = frames(o2)
            best = net(x2).argmax(1, keepdim=True)
            y = r + GAMMA * d * target(x2).gather(1, best).squeeze(1)
        loss = F.huber_loss(q, y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        steps[0] += 1
        if steps[0] % TARGET_PERIOD == 0:
            target.load_state_dict(net.state_dict())
        return loss.item()

    return step


def minimal_bcq_step(batch: Transition):
    """Discrete BCQ as rlu computes it (shared torso, Q and imitation heads), no wrapper."""

    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            self.torso, self.q, self.pi = nature_cnn(), head(), head()

        def forward(self, x):
            f = self.torso(x)
            return self.q(f), self.pi(f)

    net, target = Net(), Net()
    target.load_state_dict(net.state_dict())
    opt = torch.optim.Adam(net.parameters(), lr=LR, eps=EPS)
    o = torch.from_numpy(batch.observation)
    o2 = torch.from_numpy(batch.next_observation)
    a, r, d = (torch.from_numpy(x) for x in (batch.action, batch.reward, batch.discount))
    log_threshold = float(np.log(0.5))

    def frames(x):
        x = x.permute(0, 3, 1, 2).contiguous(memory_format=torch.channels_last)
        return x.float().mul_(1 / 255)

    def step():
        q_all, logits = net(frames(o))
        q = q_all.gather(1, a[:, None]).squeeze(1)
        with torch.no_grad():
            x2 = frames(o2)
            q2, logits2 = net(x2)
            allowed = logits2 - logits2.max(1, keepdim=True).values >= log_threshold
            best = q2.masked_fill(~allowed, float("-inf")).argmax(1, keepdim=True)
            y = r + GAMMA * d * target(x2)[0].gather(1, best).squeeze(1)
        loss = F.huber_loss(q, y) + F.cross_entropy(logits, a) + 1e-2 * logits.pow(2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return loss.item()

    return step


# ----------------------------------------------------------------------------- d3rlpy


def d3rlpy_step(kind: str, batch: Transition):
    import d3rlpy
    from d3rlpy.dataset import TransitionMiniBatch

    common = dict(
        batch_size=len(batch.action),
        learning_rate=LR,
        gamma=GAMMA,
        target_update_interval=TARGET_PERIOD,
        observation_scaler=d3rlpy.preprocessing.PixelObservationScaler(),
        optim_factory=d3rlpy.optimizers.AdamFactory(eps=EPS),
    )
    if kind == "DiscreteBCQ":
        config = d3rlpy.algos.DiscreteBCQConfig(action_flexibility=0.5, **common)
    else:
        config = getattr(d3rlpy.algos, f"{kind}Config")(**common)
    algo = config.create(device="cpu:0")
    algo.create_impl((4, 84, 84), NUM_ACTIONS)

    def chw(x):  # d3rlpy takes channel-first float32 (its samplers cast uint8 to float32)
        return np.ascontiguousarray(x.transpose(0, 3, 1, 2)).astype(np.float32)

    size = len(batch.action)
    mini = TransitionMiniBatch(
        observations=chw(batch.observation),
        actions=batch.action.astype(np.float32)[:, None],
        rewards=batch.reward[:, None],
        next_observations=chw(batch.next_observation),
        next_actions=batch.next_action.astype(np.float32)[:, None],
        terminals=(1.0 - batch.discount)[:, None],
        intervals=np.ones((size, 1), np.float32),
        transitions=[],
    )
    return lambda: algo.update(mini)


# ----------------------------------------------------------------------------- timing


def time_rounds(steps: dict, rounds: int, updates: int, warmup: int) -> dict[str, float]:
    for step in steps.values():
        for _ in range(warmup):
            step()
    per_round: dict[str, list[float]] = {name: [] for name in steps}
    order = np.random.default_rng(0)
    for _ in range(rounds):
        # a fresh order every round, so no contestant always runs first after a quiet spell
        for name in order.permutation(list(steps)):
            step = steps[name]
            start = time.perf_counter()
            for _ in range(updates):
                step()
            per_round[name].append(updates / (time.perf_counter() - start))
    return {name: statistics.median(v) for name, v in per_round.items()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--updates", type=int, default=5, help="updates per contestant per round")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument(
        "--threads", type=int, default=0, help="torch threads (0: torch's default, one per core)"
    )
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)

    batch = make_batch(args.batch)
    steps = {
        "rlu dqn": rlu_step("dqn", batch),
        "minimal dqn": minimal_dqn_step(batch),
        "rlu bcq": rlu_step("bcq", batch),
        "minimal bcq": minimal_bcq_step(batch),
    }
    try:
        import d3rlpy  # noqa: F401

        have_d3rlpy = True
        steps["d3rlpy DoubleDQN"] = d3rlpy_step("DoubleDQN", batch)
        steps["d3rlpy DQN"] = d3rlpy_step("DQN", batch)
        steps["d3rlpy DiscreteBCQ"] = d3rlpy_step("DiscreteBCQ", batch)
    except ImportError:
        have_d3rlpy = False
        print("d3rlpy not installed: only the minimal-loop comparison runs")

    print(
        f"batch {args.batch}, Nature CNN, {torch.get_num_threads()} torch threads, "
        f"{args.rounds} rounds x {args.updates} updates (median round)"
    )
    rates = time_rounds(steps, args.rounds, args.updates, args.warmup)
    for name, rate in rates.items():
        print(f"  {name:20s} {rate:8.2f} updates/s")
    print("ratios (target: >= 1.5x d3rlpy, >= 0.90 of the minimal loop):")
    if have_d3rlpy:
        r = rates["rlu dqn"] / rates["d3rlpy DoubleDQN"]
        print(f"  rlu dqn / d3rlpy DoubleDQN      {r:5.2f}x")
        r = rates["rlu dqn"] / rates["d3rlpy DQN"]
        print(f"  rlu dqn / d3rlpy DQN            {r:5.2f}x  (d3rlpy: no double-Q forward)")
        r = rates["rlu bcq"] / rates["d3rlpy DiscreteBCQ"]
        print(f"  rlu bcq / d3rlpy DiscreteBCQ    {r:5.2f}x")
    print(f"  rlu dqn / minimal dqn           {rates['rlu dqn'] / rates['minimal dqn']:5.2f}")
    print(f"  rlu bcq / minimal bcq           {rates['rlu bcq'] / rates['minimal bcq']:5.2f}")


if __name__ == "__main__":
    main()
