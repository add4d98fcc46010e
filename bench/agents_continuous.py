"""Updates per second of rlu's BC and BCQ vs d3rlpy's, and vs a minimal PyTorch loop.

    .venv-bench/bin/python bench/agents_continuous.py            # d3rlpy in the bench venv
    .venv/bin/python bench/agents_continuous.py --no-d3rlpy      # rlu vs the minimal loop only

Set up the bench venv with torch 2.13.0 first (so pip keeps the CPU build), then d3rlpy and rlu:
``python -m venv .venv-bench && .venv-bench/bin/pip install torch==2.13.0 && .venv-bench/bin/pip
install d3rlpy && .venv-bench/bin/pip install -e .``

Same data (walker_walk-shaped: 24 observation features in three keys, 6 actions), same batch,
same network sizes, same CPU threads for all three:
- BC: rlu's BC with a 256-wide residual MLP (input layer + 2 residual layers) and the 5-component
  mixture head; d3rlpy's BC ``policy_type="stochastic"`` (one Gaussian: it has no mixture) with a
  256-256-256 ReLU encoder; the minimal loop is rlu's maths (residual MLP, mixture NLL, Adam)
  written out by hand on tensors that are already in memory.
- BCQ: the original architecture (actor and critics 400-300, VAE 750-750, 10 sampled actions,
  lambda 0.75, phi 0.05, tau 0.005) in all three; d3rlpy's ``n_action_samples=10`` to match.

Batches are sampled before timing (rlu's from its own store through ``TransitionView``, d3rlpy's
from its replay buffer), so the figures are learner updates only; numpy -> torch conversion is
inside each library's ``update`` and so is timed. Figures are updates per second of process CPU
time (one intra-op thread by default, so this equals wall time on an idle machine), the best of
``--repeats`` interleaved runs, because the machine this was written on is shared and noisy.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from rlu.agents import common, make_agent
from rlu.agents import networks as nets
from rlu.data import DatasetWriter, Schema, make_episode, open_dataset
from rlu.data.views import TransitionView
from rlu.types import ArraySpec, BoundedSpec

OBS = {
    "orientations": ArraySpec((14,), "float32"),
    "height": ArraySpec((1,), "float32"),
    "velocity": ArraySpec((9,), "float32"),
}
ACTION = BoundedSpec((6,), "float32", -1.0, 1.0)
OBS_DIM, ACT_DIM = 24, 6
BC_CONFIG = dict(  # on the paper preset; sizes and components from the command line
    hidden_size=256, num_layers=2, learning_rate=1e-3, mixture_components=5
)
BCQ_CONFIG: dict = {}  # the paper preset networks (400-300, 750-750)


def make_data(path, episodes: int, length: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    with DatasetWriter(path, Schema(OBS, ACTION), {"source": "bench random"}) as w:
        for _ in range(episodes):
            obs = {k: rng.standard_normal((length + 1, *s.shape)).astype(np.float32)
                   for k, s in OBS.items()}  # fmt: skip
            act = rng.uniform(-1, 1, (length, ACT_DIM)).astype(np.float32)
            w.append(make_episode(obs, act, rng.random(length).astype(np.float32), False))
    return open_dataset(path)


def rlu_batches(ds, batch: int, count: int, seed: int = 0):
    view, rng = TransitionView(ds), np.random.default_rng(seed)
    return [view.batch(rng.integers(0, len(view), batch)) for _ in range(count)]


def timed(update, batches, warmup: int) -> float:
    for b in batches[:warmup]:
        update(b)
    # Process CPU time, not wall time: on a shared machine the wall clock mostly measures the
    # neighbours. With one intra-op thread the two agree on an idle machine.
    start = time.process_time()
    for b in batches[warmup:]:
        update(b)
    return (len(batches) - warmup) / (time.process_time() - start)


# --- minimal PyTorch loops: the same maths, no agent around it ---------------------------------
def minimal_bc(batches, seed: int = 0):
    torch.manual_seed(seed)
    k, h = BC_CONFIG["mixture_components"], BC_CONFIG["hidden_size"]
    inp = nn.Linear(OBS_DIM, h)
    blocks = nn.ModuleList(
        nn.Sequential(nn.ELU(), nn.Linear(h, h), nn.ELU(), nn.Linear(h, h)) for _ in range(1)
    )
    norms = nn.ModuleList([nn.LayerNorm(h)])
    head = nn.Linear(h, k * (1 + 2 * ACT_DIM))
    params = [*inp.parameters(), *blocks.parameters(), *norms.parameters(), *head.parameters()]
    opt = torch.optim.Adam(params, lr=BC_CONFIG["learning_rate"], fused=True)
    data = [
        (torch.cat([torch.as_tensor(b.observation[key]) for key in sorted(OBS)], -1),
         torch.as_tensor(b.action))
        for b in batches
    ]  # fmt: skip

    def update(d):
        x, a = d
        z = inp(x)
        for block, norm in zip(blocks, norms, strict=True):
            z = norm(z + block(z))
        out = head(F.elu(z))
        logits = out[:, :k]
        rest = out[:, k:].reshape(-1, k, 2, ACT_DIM)
        mean, std = rest[:, :, 0], F.softplus(rest[:, :, 1]) + 1e-3
        zz = (a[:, None] - mean) / std
        comp = (-0.5 * zz * zz - std.log() - 0.5 * math.log(2 * math.pi)).sum(-1)
        loss = -torch.logsumexp(F.log_softmax(logits, -1) + comp, -1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return update, data


def minimal_bcq(batches, seed: int = 0):
    torch.manual_seed(seed)
    g = torch.Generator().manual_seed(seed)
    s, a, lat = OBS_DIM, ACT_DIM, 2 * ACT_DIM

    def mlp(i, sizes, o):
        return nets.mlp(i, sizes, o)

    actor, q1, q2 = mlp(s + a, (400, 300), a), mlp(s + a, (400, 300), 1), mlp(s + a, (400, 300), 1)
    enc, dec = mlp(s + a, (750, 750), 2 * lat), mlp(s + lat, (750, 750), a)
    t_actor, t_q1, t_q2 = common.frozen_copy(actor), common.frozen_copy(q1), common.frozen_copy(q2)
    opt_a = torch.optim.Adam(actor.parameters(), lr=1e-3, fused=True)
    critic_params = [*q1.parameters(), *q2.parameters()]
    opt_c = torch.optim.Adam(critic_params, lr=1e-3, fused=True)
    opt_v = torch.optim.Adam([*enc.parameters(), *dec.parameters()], lr=1e-3, fused=True)
    online = [*actor.parameters(), *q1.parameters(), *q2.parameters()]
    target = [*t_actor.parameters(), *t_q1.parameters(), *t_q2.parameters()]

    def cat(obs):
        return torch.cat([torch.as_tensor(obs[key]) for key in sorted(OBS)], -1)

    data = [
        (cat(b.observation), torch.as_tensor(b.action), torch.as_tensor(b.reward),
         torch.as_tensor(b.discount), cat(b.next_observation))
        for b in batches
    ]  # fmt: skip

    def decode(x):
        zz = torch.randn((x.shape[0], lat), generator=g).clamp(-0.5, 0.5)
        return torch.tanh(dec(torch.cat([x, zz], -1)))

    def perturb(net, x, act):
        return (act + 0.05 * torch.tanh(net(torch.cat([x, act], -1)))).clamp(-1, 1)

    def update(d):
        x, act, r, disc, nx = d
        mean, log_std = enc(torch.cat([x, act], -1)).chunk(2, -1)
        std = log_std.clamp(-4, 15).exp()
        zz = mean + std * torch.randn(std.shape, generator=g)
        recon = torch.tanh(dec(torch.cat([x, zz], -1)))
        kl = -0.5 * (1 + torch.log(std.pow(2)) - mean.pow(2) - std.pow(2)).mean()
        loss_v = F.mse_loss(recon, act) + 0.5 * kl
        opt_v.zero_grad(set_to_none=True)
        loss_v.backward()
        opt_v.step()
        with torch.no_grad():
            nxr = nx.repeat_interleave(10, 0)
            na = perturb(t_actor, nxr, decode(nxr))
            sa = torch.cat([nxr, na], -1)
            a1, a2 = t_q1(sa).squeeze(-1), t_q2(sa).squeeze(-1)
            qt = 0.75 * torch.minimum(a1, a2) + 0.25 * torch.maximum(a1, a2)
            y = r + 0.99 * disc * qt.reshape(-1, 10).amax(1)
        sa = torch.cat([x, act], -1)
        loss_c = (q1(sa).squeeze(-1) - y).pow(2).mean() + (q2(sa).squeeze(-1) - y).pow(2).mean()
        opt_c.zero_grad(set_to_none=True)
        loss_c.backward()
        opt_c.step()
        with torch.no_grad():
            sampled = decode(x)
        loss_a = -q1(torch.cat([x, perturb(actor, x, sampled)], -1)).mean()
        opt_a.zero_grad(set_to_none=True)
        loss_a.backward(inputs=list(actor.parameters()))
        opt_a.step()
        with torch.no_grad():
            torch._foreach_lerp_(target, online, 0.005)

    return update, data


# --- d3rlpy ------------------------------------------------------------------------------------
def d3rlpy_setup(algo: str, ds, batch: int, count: int):
    import d3rlpy
    from d3rlpy.models.encoders import VectorEncoderFactory

    obs = np.concatenate([np.asarray(ds.column(f"observation/{k}")) for k in sorted(OBS)], -1)
    last = np.asarray(ds.column("is_last"))
    # d3rlpy wants transitions without the final observation row of each episode.
    dataset = d3rlpy.dataset.MDPDataset(
        observations=obs[~last],
        actions=np.asarray(ds.column("action"))[~last],
        rewards=np.asarray(ds.column("reward"))[~last],
        terminals=np.zeros(int((~last).sum())),
        timeouts=np.asarray(np.roll(last, -1))[~last].astype(float),
    )
    if algo == "bc":
        config = d3rlpy.algos.BCConfig(
            batch_size=batch,
            learning_rate=BC_CONFIG["learning_rate"],
            policy_type="stochastic",
            encoder_factory=VectorEncoderFactory(hidden_units=[BC_CONFIG["hidden_size"]] * 3),
        )
    else:
        config = d3rlpy.algos.BCQConfig(
            batch_size=batch,
            actor_encoder_factory=VectorEncoderFactory(hidden_units=[400, 300]),
            critic_encoder_factory=VectorEncoderFactory(hidden_units=[400, 300]),
            imitator_encoder_factory=VectorEncoderFactory(hidden_units=[750, 750]),
            n_action_samples=10,
        )
    agent = config.create(device="cpu:0")
    agent.build_with_dataset(dataset)
    return agent.update, [dataset.sample_transition_batch(batch) for _ in range(count)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--updates", type=int, default=200, help="timed updates per run")
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--repeats", type=int, default=3, help="runs per contender; best one counts")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads for all")
    p.add_argument("--no-d3rlpy", action="store_true", help="skip d3rlpy (not installed)")
    p.add_argument("--algos", nargs="+", default=["bc", "bcq"])
    p.add_argument("--bc-hidden", type=int, default=256, help="BC width (all three contenders)")
    p.add_argument("--bc-components", type=int, default=5,
                   help="mixture components of rlu's BC and its minimal loop (1: one Gaussian, "
                        "d3rlpy's policy)")  # fmt: skip
    args = p.parse_args()
    BC_CONFIG["hidden_size"] = args.bc_hidden
    BC_CONFIG["mixture_components"] = args.bc_components
    torch.set_num_threads(args.threads)
    count = args.updates + args.warmup
    print(f"torch {torch.__version__}, {args.threads} thread(s), batch {args.batch}, "
          f"{args.updates} timed updates, best of {args.repeats}")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        ds = make_data(f"{tmp}/data", episodes=50, length=1000)
        batches = rlu_batches(ds, args.batch, count)
        for algo in args.algos:
            overrides = BC_CONFIG if algo == "bc" else BCQ_CONFIG
            contenders = {}
            agent = make_agent(algo, OBS, ACTION, "paper", 0, batch_size=args.batch, **overrides)
            contenders["rlu"] = (agent.update, batches)
            adam = common.adam
            common.adam = lambda params, lr, eps=1e-8: torch.optim.Adam(
                params, lr=lr, eps=eps, foreach=True
            )
            slow = make_agent(algo, OBS, ACTION, "paper", 0, batch_size=args.batch, **overrides)
            common.adam = adam
            contenders["rlu, foreach Adam"] = (slow.update, batches)
            contenders["minimal loop"] = (minimal_bc if algo == "bc" else minimal_bcq)(batches)
            if not args.no_d3rlpy:
                contenders["d3rlpy"] = d3rlpy_setup(algo, ds, args.batch, count)
            best = {name: 0.0 for name in contenders}
            for _ in range(args.repeats):
                for name, (update, data) in contenders.items():
                    best[name] = max(best[name], timed(update, data, args.warmup))
            print(f"\n{algo.upper()}")
            for name, ups in best.items():
                print(f"  {name:20s} {ups:8.1f} updates per CPU-second")
            ratio = best["rlu"] / best["minimal loop"]
            print(f"  rlu / minimal loop   {ratio:8.2f}  (target >= 0.90)")
            if "d3rlpy" in best:
                ratio = best["rlu"] / best["d3rlpy"]
                print(f"  rlu / d3rlpy         {ratio:8.2f}x (target >= 1.5x)")


if __name__ == "__main__":
    main()
