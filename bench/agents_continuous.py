"""Updates per second of every continuous rlu agent vs a minimal PyTorch loop with the same maths,
and vs d3rlpy for the algorithms both have (CPU, one run, interleaved).

    .venv-bench/bin/python bench/agents_continuous.py                    # every agent
    .venv-bench/bin/python bench/agents_continuous.py --agents bc bcq --rounds 9
    .venv/bin/python bench/agents_continuous.py --no-d3rlpy              # without d3rlpy

d3rlpy lives in the bench venv (bench/README.md), never in rlu's dependencies. Data: one rlu
dataset shaped like control_suite/walker_walk (24 observation features in three keys, 6 actions,
50 episodes of 1000 steps, random values), written once with rlu's writer; every contestant
samples the same steps its own way:

- rlu: ``make_sampler(dataset, agent.batch_spec)`` (the memory-mapped store) and
  ``agent.update(batch)``, the training loop's two calls; the agent is built by name with
  ``rlu.agents.make_agent`` (an agent of the list missing from the registry is skipped with a
  line saying so);
- minimal loop: the observation keys concatenated once into one in-RAM array, batches by numpy
  fancy indexing (the n-step sum in numpy where the agent asks for it), and the agent's maths
  written out straight on plain modules: same network sizes (read from the rlu agent's config),
  the same losses, fused Adam, the same target updates, no metrics, no checks;
- d3rlpy 2.8.1: its replay buffer over the same episodes (observation keys concatenated) and
  ``algo.update``, with rlu's widths, learning rates and constants.

Architectures (the third point of issue 17): rlu's BC preset is the paper's residual MLP with a
5-component Gaussian mixture; d3rlpy's BC is one Gaussian on a plain MLP. ``bc`` runs both
comparisons: "bc (preset)" (rlu's mixture on the residual MLP against d3rlpy's default 256-256
MLP) and "bc (same network)" (rlu with one mixture component, d3rlpy with rlu's residual MLP as
its encoder: the same layers, a Gaussian head each; the losses still differ: rlu maximises the
log-likelihood, d3rlpy's stochastic BC regresses a sampled action onto the data's). BCQ, IQL,
CQL and CRR run with d3rlpy's vector encoders at rlu's widths. d4pg, brac, rabm and dmpo (the
RWRL data's behaviour agent) have no d3rlpy counterpart: rlu and its minimal loop only.

Timing (bench/agents_timing.py): "sample + update" and "update only", updates per CPU-second of
the process (and wall), one over the median time of an update in many short interleaved rounds,
one torch thread unless ``--threads``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from agents_timing import (  # noqa: E402
    Contestant,
    bf16,
    cpu_line,
    load_line,
    report,
    summary,
    time_contestants,
)

from rlu.agents import AGENTS, make_agent  # noqa: E402
from rlu.data import DatasetWriter, Schema, make_episode, make_sampler, open_dataset  # noqa: E402
from rlu.types import ArraySpec, BoundedSpec  # noqa: E402

OBS = {
    "orientations": ArraySpec((14,), "float32"),
    "height": ArraySpec((1,), "float32"),
    "velocity": ArraySpec((9,), "float32"),
}
ACTION = BoundedSpec((6,), "float32", -1.0, 1.0)
OBS_DIM, ACT_DIM = 24, 6
LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)

# Sizes per agent, on the paper preset (batch 256 throughout). Where the paper's full size would
# take seconds per update on a 2-core machine (BC's and RABM's 8 x 1024 residual MLPs) the bench
# takes 256-wide, 2-layer ones; the rest are the paper's own networks.
SETTINGS: dict[str, dict] = {
    "bc": dict(hidden_size=256, num_layers=2, learning_rate=1e-3, batch_size=256),
    "bcq": dict(batch_size=256, target_update_period=0),  # Polyak, as the original and d3rlpy
    "d4pg": dict(),
    "brac": dict(behaviour_steps=0),  # time the full update, not the behaviour-cloning phase
    "rabm": dict(hidden_size=256, num_layers=2, batch_size=256, num_samples=10),
    "crr": dict(hidden_size=256, num_layers=2),  # the paper's 8 x 1024 as BC's: 256 x 2 here
    "iql": dict(),
    "cql": dict(bc_steps=0),  # time the full update, not the behaviour-cloning phase
    "dmpo": dict(),  # the RWRL data's behaviour agent (online in rlu generate): its learner step
}


# ----------------------------------------------------------------------------- data


def make_data(path, episodes: int, length: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    with DatasetWriter(path, Schema(OBS, ACTION), {"source": "bench random"}) as w:
        for _ in range(episodes):
            obs = {k: rng.standard_normal((length + 1, *s.shape)).astype(np.float32)
                   for k, s in OBS.items()}  # fmt: skip
            act = rng.uniform(-1, 1, (length, ACT_DIM)).astype(np.float32)
            w.append(make_episode(obs, act, rng.random(length).astype(np.float32), False))
    return open_dataset(path)


class MinimalSampler:
    """The in-RAM numpy bound: flat arrays, valid start steps, fancy indexing, n-step in numpy."""

    def __init__(self, ds, batch: int, n_step: int = 1, gamma: float = 1.0, seed: int = 0):
        cols = [np.asarray(ds.column(f"observation/{k}")) for k in sorted(OBS)]
        self.obs = np.concatenate(cols, -1)
        self.action = np.array(ds.column("action"))
        self.reward = np.array(ds.column("reward"))
        self.discount = np.array(ds.column("discount"))
        start, length = np.asarray(ds.start), np.asarray(ds.length)
        # no terminal in this data: step t holds an n-step transition if t + n is in its segment
        starts = [s + np.arange(n - n_step) for s, n in zip(start, length, strict=True)]
        self.starts = np.concatenate(starts)
        self.batch, self.n = batch, n_step
        self.powers = gamma ** np.arange(n_step, dtype=np.float32)
        self.rng = np.random.default_rng(seed)

    def sample(self):
        t = self.starts[self.rng.integers(0, len(self.starts), self.batch)]
        if self.n == 1:
            r, d = self.reward[t], self.discount[t]
        else:
            w = t[:, None] + np.arange(self.n)
            dw = self.discount[w]
            alive = np.cumprod(np.concatenate([np.ones_like(dw[:, :1]), dw[:, :-1]], 1), 1)
            r, d = (self.reward[w] * alive * self.powers).sum(1), dw.prod(1)
        return self.obs[t], self.action[t], r, d, self.obs[t + self.n]


def tensors(batch):
    return tuple(torch.from_numpy(x) for x in batch)


# ----------------------------------------------------------------------------- minimal loops
# Each builds plain modules of the rlu config's sizes and returns update(numpy batch) doing the
# agent's maths straight through: the no-overhead bound for that agent.


def adam(params, lr: float) -> torch.optim.Adam:
    return torch.optim.Adam(params, lr=lr, fused=True)


def step(opt, loss, inputs=None) -> None:
    opt.zero_grad(set_to_none=True)
    loss.backward(inputs=inputs)
    opt.step()


def copy_into(target: nn.Module, source: nn.Module) -> None:
    with torch.no_grad():
        torch._foreach_copy_(list(target.parameters()), list(source.parameters()))


def lerp_into(target: nn.Module, source: nn.Module, tau: float) -> None:
    with torch.no_grad():
        torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)


def step_together(opts, loss, clipped=(), max_norm: float = 0.0) -> None:
    """One backward for several optimisers (each loss reaches only its own parameters), the
    parameter groups in ``clipped`` clipped to global norm ``max_norm``, then every step."""
    for opt in opts:
        opt.zero_grad(set_to_none=True)
    loss.backward()
    for params in clipped:
        nn.utils.clip_grad_norm_(params, max_norm, foreach=True)
    for opt in opts:
        opt.step()


def copy_every(steps: list[int], period: int, pairs: dict) -> None:
    """Count the update; hard-copy each source into its target every ``period`` updates."""
    steps[0] += 1
    if steps[0] % period == 0:
        for target, source in pairs.items():
            copy_into(target, source)


def frozen(module: nn.Module) -> nn.Module:
    import copy

    return copy.deepcopy(module).requires_grad_(False)


class ResidualMLP(nn.Module):
    def __init__(self, inp: int, hidden: int, layers: int):
        super().__init__()
        self.inp = nn.Linear(inp, hidden)
        self.blocks = nn.ModuleList(
            nn.Sequential(nn.ELU(), nn.Linear(hidden, hidden), nn.ELU(), nn.Linear(hidden, hidden))
            for _ in range(layers // 2)
        )
        self.norms = nn.ModuleList(nn.LayerNorm(hidden) for _ in range(layers // 2))

    def forward(self, x):
        h = self.inp(x)
        for block, norm in zip(self.blocks, self.norms, strict=True):
            h = norm(h + block(h))
        return F.elu(h)


def relu_mlp(inp: int, sizes, out: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for size in sizes:
        layers += [nn.Linear(inp, size), nn.ReLU()]
        inp = size
    return nn.Sequential(*layers, nn.Linear(inp, out))


def gaussian_log_prob(mean, std, x):
    z = (x - mean) / std
    return (-0.5 * z * z - std.log() - LOG_SQRT_2PI).sum(-1)


def mixture(out, k: int):
    logits = out[..., :k]
    rest = out[..., k:].reshape(*out.shape[:-1], k, 2, ACT_DIM)
    return logits, rest[..., 0, :], F.softplus(rest[..., 1, :]) + 1e-3


def minimal_bc(c, seed: int = 0):
    torch.manual_seed(seed)
    k = c.mixture_components
    net = nn.Sequential(
        ResidualMLP(OBS_DIM, c.hidden_size, c.num_layers),
        nn.Linear(c.hidden_size, k * (1 + 2 * ACT_DIM)),
    )
    opt = adam(net.parameters(), c.learning_rate)

    def update(batch):
        x, a, *_ = tensors(batch)
        logits, mean, std = mixture(net(x), k)
        comp = gaussian_log_prob(mean, std, a[:, None])
        loss = -torch.logsumexp(F.log_softmax(logits, -1) + comp, -1).mean()
        step(opt, loss)
        return loss.item()

    return update, net


def minimal_bcq(c, seed: int = 0):
    torch.manual_seed(seed)
    g = torch.Generator().manual_seed(seed)
    lat = 2 * ACT_DIM
    sa = OBS_DIM + ACT_DIM
    actor = relu_mlp(sa, c.actor_layers, ACT_DIM)
    q1, q2 = relu_mlp(sa, c.critic_layers, 1), relu_mlp(sa, c.critic_layers, 1)
    enc, dec = relu_mlp(sa, c.vae_layers, 2 * lat), relu_mlp(OBS_DIM + lat, c.vae_layers, ACT_DIM)
    online = nn.ModuleList([actor, q1, q2])
    target = frozen(online)
    t_actor, t_q1, t_q2 = target
    opt_a, opt_c = (
        adam(actor.parameters(), c.actor_lr),
        adam([*q1.parameters(), *q2.parameters()], c.critic_lr),
    )
    opt_v = adam([*enc.parameters(), *dec.parameters()], c.vae_lr)
    actor_params = list(actor.parameters())
    steps = [0]
    rows = c.cpu_slice_rows or c.num_samples * c.batch_size

    def decode(x):
        z = torch.randn((x.shape[0], lat), generator=g).clamp(-0.5, 0.5)
        return torch.tanh(dec(torch.cat([x, z], -1)))

    def perturb(net, x, a):
        return (a + c.phi * torch.tanh(net(torch.cat([x, a], -1)))).clamp(-1, 1)

    def update(batch):
        x, a, r, d, nx = tensors(batch)
        mean, log_std = enc(torch.cat([x, a], -1)).chunk(2, -1)
        std = log_std.clamp(-4, 15).exp()
        recon = torch.tanh(dec(torch.cat([x, mean + std * torch.randn(std.shape, generator=g)],
                                         -1)))  # fmt: skip
        kl = -0.5 * (1 + torch.log(std.pow(2)) - mean.pow(2) - std.pow(2)).mean()
        step(opt_v, F.mse_loss(recon, a) + 0.5 * kl)
        with torch.no_grad():  # in slices of c.cpu_slice_rows rows, as rlu's BCQ on a CPU
            nxr = nx.repeat_interleave(c.num_samples, 0)
            z = torch.randn((nxr.shape[0], lat), generator=g).clamp(-0.5, 0.5)
            values = []
            for nx_i, z_i in zip(nxr.split(rows), z.split(rows), strict=True):
                na = perturb(t_actor, nx_i, torch.tanh(dec(torch.cat([nx_i, z_i], -1))))
                nsa = torch.cat([nx_i, na], -1)
                v1, v2 = t_q1(nsa).squeeze(-1), t_q2(nsa).squeeze(-1)
                values.append(
                    c.lmbda * torch.minimum(v1, v2) + (1 - c.lmbda) * torch.maximum(v1, v2)
                )
            v = torch.cat(values)
            y = r + c.gamma * d * v.reshape(-1, c.num_samples).amax(1)
        xa = torch.cat([x, a], -1)
        loss_c = (q1(xa).squeeze(-1) - y).pow(2).mean() + (q2(xa).squeeze(-1) - y).pow(2).mean()
        step(opt_c, loss_c)
        with torch.no_grad():
            sampled = decode(x)
        loss_a = -q1(torch.cat([x, perturb(actor, x, sampled)], -1)).mean()
        step(opt_a, loss_a, actor_params)
        steps[0] += 1
        if c.target_update_period > 0:
            if steps[0] % c.target_update_period == 0:
                copy_into(target, online)
        else:
            lerp_into(target, online, c.tau)
        return loss_c.item()

    return update, nn.ModuleList([online, enc, dec])


def layer_norm_mlp(inp: int, sizes) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Linear(inp, sizes[0]), nn.LayerNorm(sizes[0]), nn.Tanh()]
    for i, size in enumerate(sizes[1:]):
        layers += [nn.Linear(sizes[i], size), nn.ELU()]
    return nn.Sequential(*layers)


def project(values, probs, atoms):
    delta = (atoms[-1] - atoms[0]) / (atoms.shape[0] - 1)
    v = values.clamp(atoms[0], atoms[-1])
    w = (1.0 - (v[..., None] - atoms).abs() / delta).clamp(min=0.0)
    return (probs[..., None] * w).sum(-2)


def minimal_d4pg(c, seed: int = 0):
    torch.manual_seed(seed)
    policy = nn.Sequential(layer_norm_mlp(OBS_DIM, c.policy_layers),
                           nn.Linear(c.policy_layers[-1], ACT_DIM), nn.Tanh())  # fmt: skip
    critic = nn.Sequential(layer_norm_mlp(OBS_DIM + ACT_DIM, c.critic_layers),
                           nn.Linear(c.critic_layers[-1], c.num_atoms))  # fmt: skip
    t_policy, t_critic = frozen(policy), frozen(critic)
    atoms = torch.linspace(c.vmin, c.vmax, c.num_atoms)
    opt_p, opt_c = adam(policy.parameters(), c.policy_lr), adam(critic.parameters(), c.critic_lr)
    policy_params = list(policy.parameters())
    bootstrap = c.gamma**c.n_step
    steps = [0]

    def update(batch):
        x, a, r, d, nx = tensors(batch)
        with torch.no_grad():
            t_logits = t_critic(torch.cat([nx, t_policy(nx)], -1))
            values = r[:, None] + bootstrap * d[:, None] * atoms
            target = project(values, torch.softmax(t_logits, -1), atoms)
        loss_c = -(target * F.log_softmax(critic(torch.cat([x, a], -1)), -1)).sum(-1).mean()
        step(opt_c, loss_c)
        q = (torch.softmax(critic(torch.cat([x, policy(x)], -1)), -1) * atoms).sum(-1)
        step(opt_p, -q.mean(), policy_params)
        steps[0] += 1
        if steps[0] % c.target_update_period == 0:
            copy_into(t_policy, policy)
            copy_into(t_critic, critic)
        return loss_c.item()

    return update, nn.ModuleList([policy, critic])


def minimal_dmpo(c, seed: int = 0):
    """DMPO: the target critic on N target-policy actions per next state (whole samples of
    c.cpu_slice_rows rows at a time, as rlu on a CPU), the projected critic loss on their mean
    distribution, MPO's E-step and action-penalty E-step, the decoupled M-step with per-dimension
    KL multipliers, one backward, global-norm clipping, hard target copies."""
    torch.manual_seed(seed)
    g = torch.Generator().manual_seed(seed)
    width = c.policy_layers[-1]
    policy = nn.ModuleList([layer_norm_mlp(OBS_DIM, c.policy_layers), nn.Linear(width, ACT_DIM),
                            nn.Linear(width, ACT_DIM)])  # fmt: skip
    with torch.no_grad():
        for layer in policy[1:]:
            layer.weight.mul_(1e-4)
            layer.bias.zero_()
    critic = nn.Sequential(layer_norm_mlp(OBS_DIM + ACT_DIM, c.critic_layers),
                           nn.Linear(c.critic_layers[-1], c.num_atoms))  # fmt: skip
    t_policy, t_critic = frozen(policy), frozen(critic)
    duals = nn.ParameterList([
        nn.Parameter(torch.tensor(c.init_log_temperature)),
        nn.Parameter(torch.tensor(c.init_log_temperature)),
        nn.Parameter(torch.full((ACT_DIM,), c.init_log_alpha_mean)),
        nn.Parameter(torch.full((ACT_DIM,), c.init_log_alpha_stddev)),
    ])  # fmt: skip
    opts = (adam(policy.parameters(), c.policy_lr), adam(critic.parameters(), c.critic_lr),
            adam(duals.parameters(), c.dual_lr))  # fmt: skip
    atoms = torch.linspace(c.vmin, c.vmax, c.num_atoms)
    scale, n, bootstrap = c.init_scale / math.log(2.0), c.num_samples, c.gamma**c.n_step
    per = max(1, (c.cpu_slice_rows or n * c.batch_size) // c.batch_size)
    steps = [0]

    def pi(net, x):
        h = net[0](x)
        return net[1](h), F.softplus(net[2](h)) * scale + c.min_scale

    def e_step(q, temperature, epsilon):
        dual = temperature * (epsilon + (torch.logsumexp(q / temperature, 0) - math.log(n)).mean())
        return torch.softmax(q / temperature, 0).detach(), dual

    def kl(mean_p, std_p, mean_q, std_q):  # per dimension
        return (
            (std_q / std_p).log()
            + (std_p.pow(2) + (mean_p - mean_q).pow(2)) / (2 * std_q.pow(2))
            - 0.5
        )

    def update(batch):
        x, a, r, d, nx = tensors(batch)
        with torch.no_grad():
            for p in duals:
                p.clamp_(min=-18.0)
            t_mean, t_std = pi(t_policy, nx)
            sampled = t_mean + t_std * torch.randn((n, *t_mean.shape), generator=g)
            logits = torch.cat([t_critic(torch.cat([nx.expand(k.shape[0], -1, -1),
                                                    k.clamp(-1, 1)], -1))
                                for k in sampled.split(per)])  # fmt: skip
            probs = torch.softmax(logits, -1)
            q = (probs * atoms).sum(-1)
            target = project(r[:, None] + bootstrap * d[:, None] * atoms, probs.mean(0), atoms)
        loss_c = -(target * F.log_softmax(critic(torch.cat([x, a.clamp(-1, 1)], -1)), -1)).sum(-1)
        mean, std = pi(policy, nx)
        temperature, penalty, alpha_mean, alpha_std = (F.softplus(p) + 1e-8 for p in duals)
        w, loss_t = e_step(q, temperature, c.epsilon)
        cost = -torch.linalg.vector_norm(sampled - sampled.clamp(-1, 1), dim=-1)
        pw, loss_pen = e_step(cost, penalty, c.epsilon_penalty)
        log_p = gaussian_log_prob(mean, t_std, sampled) + gaussian_log_prob(t_mean, std, sampled)
        loss_pi = -((w + pw) * log_p).sum(0).mean()
        kl_mean = kl(t_mean, t_std, mean, t_std).mean(0)
        kl_std = kl(t_mean, t_std, t_mean, std).mean(0)
        loss_kl = (alpha_mean.detach() * kl_mean).sum() + (alpha_std.detach() * kl_std).sum()
        loss_alpha = (alpha_mean * (c.epsilon_mean - kl_mean.detach())).sum() + (
            alpha_std * (c.epsilon_stddev - kl_std.detach())
        ).sum()
        loss = loss_c.mean() + loss_pi + loss_kl + loss_alpha + loss_t + loss_pen
        step_together(opts, loss, [policy.parameters(), critic.parameters()], c.max_grad_norm)
        copy_every(steps, c.target_update_period, {t_policy: policy, t_critic: critic})
        return loss_pi.item()

    return update, nn.ModuleList([policy, critic, duals])


def minimal_brac(c, seed: int = 0):
    torch.manual_seed(seed)
    g = torch.Generator().manual_seed(seed)
    clip = 1.0 - 1e-3
    policy = relu_mlp(OBS_DIM, c.policy_layers, 2 * ACT_DIM)
    behaviour = relu_mlp(OBS_DIM, c.behaviour_layers, 2 * ACT_DIM).requires_grad_(False)
    critics = nn.ModuleList([relu_mlp(OBS_DIM + ACT_DIM, c.critic_layers, 1) for _ in range(2)])
    t_critics = frozen(critics)
    opt_p, opt_c = adam(policy.parameters(), c.policy_lr), adam(critics.parameters(), c.critic_lr)
    policy_params = list(policy.parameters())
    steps = [0]

    def dist(net, x):
        mean, log_std = net(x).chunk(2, -1)
        return mean, log_std.clamp(-5.0, 2.0).exp()

    def tanh_log_prob(mean, std, u):
        log_det = 2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))
        return gaussian_log_prob(mean, std, u) - log_det.sum(-1)

    def sample(x):
        mean, std = dist(policy, x)
        u = mean + std * torch.randn((c.num_kl_samples, *mean.shape), generator=g)
        return torch.tanh(u), tanh_log_prob(mean, std, u)

    def kl(x, a, log_pi):
        mean, std = dist(behaviour, x)
        return (log_pi - tanh_log_prob(mean, std, torch.atanh(a.clamp(-clip, clip)))).mean(0)

    def q_min(nets, x, a):
        xa = torch.cat([x, a], -1)
        return torch.minimum(nets[0](xa), nets[1](xa)).squeeze(-1)

    def update(batch):
        x, a, r, d, nx = tensors(batch)
        with torch.no_grad():
            na, nlogp = sample(nx)
            y = r + c.gamma * d * (q_min(t_critics, nx, na[0]) - c.alpha * kl(nx, na, nlogp))
        xa = torch.cat([x, a], -1)
        loss_c = sum((q(xa).squeeze(-1) - y).pow(2).mean() for q in critics)
        step(opt_c, loss_c)
        sa, logp = sample(x)
        loss_a = (c.alpha * kl(x, sa, logp) - q_min(critics, x, sa[0])).mean()
        step(opt_p, loss_a, policy_params)
        steps[0] += 1
        if c.target_update_period > 0:
            if steps[0] % c.target_update_period == 0:
                copy_into(t_critics, critics)
        else:
            lerp_into(t_critics, critics, c.tau)
        return loss_c.item()

    return update, nn.ModuleList([policy, behaviour, critics])


def minimal_rabm(c, seed: int = 0):
    """RABM's feed-forward update (rlu.agents.rabm) on transitions, written out."""
    torch.manual_seed(seed)
    g = torch.Generator().manual_seed(seed)
    h, n = c.hidden_size, c.num_samples

    class Gaussian(nn.Module):
        def __init__(self):
            super().__init__()
            self.torso, self.head = ResidualMLP(OBS_DIM, h, c.num_layers), nn.Linear(h, 2 * ACT_DIM)

        def dist(self, f):
            mean, raw = self.head(f).chunk(2, -1)
            return mean, F.softplus(raw) + 1e-3

    class Critic(nn.Module):
        def __init__(self):
            super().__init__()
            self.torso = ResidualMLP(OBS_DIM, h, c.num_layers)
            self.joint, self.head = nn.Linear(h + ACT_DIM, h), nn.Linear(h, c.num_atoms)

        def logits(self, f, a):
            return self.head(F.elu(self.joint(torch.cat([f.expand(*a.shape[:-1], h), a], -1))))

    prior, policy, critic = Gaussian(), Gaussian(), Critic()
    t_policy, t_critic = frozen(policy), frozen(critic)
    duals = nn.ParameterDict({k: nn.Parameter(torch.tensor(v)) for k, v in
                              (("t", 1.0), ("mean", 1.0), ("std", 10.0))})  # fmt: skip
    atoms = torch.linspace(c.vmin, c.vmax, c.num_atoms)
    opts = [
        adam(prior.parameters(), c.prior_lr),
        adam(policy.parameters(), c.policy_lr),
        adam(critic.parameters(), c.critic_lr),
        adam(duals.parameters(), c.dual_lr),
    ]
    bootstrap = c.gamma**c.n_step
    steps = [0]

    def q_mean(logits):
        return (torch.softmax(logits, -1) * atoms).sum(-1)

    def kl(mp, sp, mq, sq):
        return (torch.log(sq / sp) + (sp.pow(2) + (mp - mq).pow(2)) / (2 * sq.pow(2)) - 0.5).sum(-1)

    def noise(mean):
        return torch.randn((n, *mean.shape), generator=g)

    def update(batch):
        x, a, r, d, nx = tensors(batch)
        pol_h, prior_h, crit_h = policy.torso(x), prior.torso(x), critic.torso(x)
        with torch.no_grad():
            tm, ts = t_policy.dist(t_policy.torso(nx))
            na = (tm + ts * noise(tm)).clamp(-1, 1)
            probs = torch.softmax(t_critic.logits(t_critic.torso(nx), na), -1).mean(0)
            target = project(r[:, None] + bootstrap * d[:, None] * atoms, probs, atoms)
        loss_critic = -(target * F.log_softmax(critic.logits(crit_h, a), -1)).sum(-1).mean()
        mean, std = policy.dist(pol_h)
        p_mean, p_std = prior.dist(prior_h)
        with torch.no_grad():
            cd = crit_h.detach()
            q_data = q_mean(critic.logits(cd, a))
            pi_a = (mean + std * noise(mean)).clamp(-1, 1)
            adv = q_data - q_mean(critic.logits(cd, pi_a)).mean(0)
            prior_a = (p_mean + p_std * noise(mean)).clamp(-1, 1)
            q_prior = q_mean(critic.logits(cd, prior_a))
            tp_mean, tp_std = t_policy.dist(t_policy.torso(x))
        w = (adv >= 0).float()
        loss_prior = -(w * gaussian_log_prob(p_mean, p_std, a)).mean()
        temp = F.softplus(duals["t"]) + 1e-8
        weights = torch.softmax(q_prior / temp, 0).detach()
        loss_temp = temp * c.epsilon + temp * (
            torch.logsumexp(q_prior / temp, 0) - math.log(n)).mean()  # fmt: skip
        fit = gaussian_log_prob(mean, tp_std, prior_a) + gaussian_log_prob(tp_mean, std, prior_a)
        loss_fit = -(weights * fit).sum(0).mean()
        kl_mean, kl_std = (
            kl(tp_mean, tp_std, mean, tp_std).mean(),
            kl(tp_mean, tp_std, tp_mean, std).mean(),
        )
        a_mean, a_std = F.softplus(duals["mean"]) + 1e-8, F.softplus(duals["std"]) + 1e-8
        loss_pol = (loss_fit + a_mean.detach() * kl_mean + a_std.detach() * kl_std
                    + a_mean * (c.epsilon_mean - kl_mean.detach())
                    + a_std * (c.epsilon_std - kl_std.detach()))  # fmt: skip
        step_together(opts, loss_critic + loss_prior + loss_pol + loss_temp)
        copy_every(steps, c.target_update_period, {t_policy: policy, t_critic: critic})
        return loss_critic.item()

    return update, nn.ModuleList([prior, policy, critic])


# The next three mirror rlu/agents/{iql,crr,cql}.py.


def minimal_iql(c, seed: int = 0):
    torch.manual_seed(seed)
    layers = c.hidden_layers
    value = relu_mlp(OBS_DIM, layers, 1)
    critics = nn.ModuleList([relu_mlp(OBS_DIM + ACT_DIM, layers, 1) for _ in range(2)])
    t_critics = frozen(critics)
    policy = relu_mlp(OBS_DIM, layers, ACT_DIM)
    log_std = nn.Parameter(torch.zeros(ACT_DIM))
    opt_v, opt_c = adam(value.parameters(), c.value_lr), adam(critics.parameters(), c.critic_lr)
    opt_p = adam([*policy.parameters(), log_std], c.actor_lr)
    steps = [0]

    def update(batch):
        x, a, r, d, nx = tensors(batch)
        xa = torch.cat([x, a], -1)
        with torch.no_grad():
            q_min = torch.minimum(t_critics[0](xa), t_critics[1](xa)).squeeze(-1)
        u = q_min - value(x).squeeze(-1)
        weight = torch.where(u > 0, c.expectile, 1.0 - c.expectile)
        step(opt_v, (weight * u.pow(2)).mean())
        with torch.no_grad():
            v, v_next = value(torch.cat([x, nx])).squeeze(-1).split(len(r))
            adv = q_min - v
            y = r * c.reward_scale + c.gamma * d * v_next
        if c.cosine_decay:
            frac = min(steps[0], c.num_steps) / c.num_steps
            opt_p.param_groups[0]["lr"] = c.actor_lr * 0.5 * (1.0 + math.cos(math.pi * frac))
        mean = torch.tanh(policy(x))
        std = log_std.clamp(c.log_std_min, c.log_std_max).exp().expand_as(mean)
        w = torch.exp(c.beta * adv).clamp(max=c.max_weight)
        step(opt_p, -(w * gaussian_log_prob(mean, std, a)).mean())
        loss_q = sum((q(xa).squeeze(-1) - y).pow(2).mean() for q in critics)
        step(opt_c, loss_q)
        lerp_into(t_critics, critics, c.tau)
        steps[0] += 1
        return loss_q.item()

    return update, nn.ModuleList([value, critics, policy, nn.ParameterList([log_std])])


def sample_mixture(logits, mean, std, num: int, g):
    """(num, B, A) actions from (B,) mixtures: a component by weight, then Gaussian noise."""
    probs = torch.softmax(logits, -1)
    idx = (
        torch.multinomial(
            probs.expand(num, *probs.shape).reshape(-1, probs.shape[-1]), 1, generator=g
        )
        .reshape(num, -1, 1, 1)
        .expand(-1, -1, 1, ACT_DIM)
    )
    mu = mean.expand(num, *mean.shape).gather(-2, idx).squeeze(-2)
    sd = std.expand(num, *std.shape).gather(-2, idx).squeeze(-2)
    return (mu + sd * torch.randn(mu.shape, generator=g)).clamp(-1.0, 1.0)  # fmt: skip


def minimal_crr(c, seed: int = 0):
    torch.manual_seed(seed)
    g = torch.Generator().manual_seed(seed)
    k, h = c.mixture_components, c.hidden_size
    policy = nn.Sequential(ResidualMLP(OBS_DIM, h, c.num_layers),
                           nn.Linear(h, k * (1 + 2 * ACT_DIM)))  # fmt: skip
    critic = nn.Sequential(ResidualMLP(OBS_DIM + ACT_DIM, h, c.num_layers),
                           nn.Linear(h, c.num_atoms))  # fmt: skip
    t_policy, t_critic = frozen(policy), frozen(critic)
    atoms = torch.linspace(c.vmin, c.vmax, c.num_atoms)
    opt_p, opt_c = adam(policy.parameters(), c.policy_lr), adam(critic.parameters(), c.critic_lr)
    p_params, c_params = list(policy.parameters()), list(critic.parameters())
    bootstrap = c.gamma
    steps = [0]

    def q_logits(net, x, a):
        return net(torch.cat([x.expand(*a.shape[:-1], OBS_DIM), a], -1))

    def q_mean(logits):
        return (torch.softmax(logits, -1) * atoms).sum(-1)

    def clipped_step(opt, loss, params):
        opt.zero_grad(set_to_none=True)
        loss.backward(inputs=params)
        if c.max_grad_norm > 0:
            nn.utils.clip_grad_norm_(params, c.max_grad_norm, foreach=True)
        opt.step()

    def update(batch):
        x, a, r, d, nx = tensors(batch)
        with torch.no_grad():
            na = sample_mixture(*mixture(t_policy(nx), k), c.num_target_samples, g)
            probs = torch.softmax(q_logits(t_critic, nx, na), -1).mean(0)
            target = project(r[:, None] + bootstrap * d[:, None] * atoms, probs, atoms)
        logits = q_logits(critic, x, a)
        loss_c = -(target * F.log_softmax(logits, -1)).sum(-1).mean()
        mix = mixture(policy(x), k)
        with torch.no_grad():
            sampled = sample_mixture(*mix, c.num_advantage_samples, g)
            q_samples = q_mean(q_logits(critic, x, sampled))
            v = q_samples.mean(0) if c.baseline == "mean" else q_samples.amax(0)
            adv = q_mean(logits) - v
            if c.advantage_weight == "exp":
                w = torch.exp(adv / c.beta).clamp(max=c.ratio_upper_bound)
            else:
                w = (adv > 0).float()
        comp = gaussian_log_prob(mix[1], mix[2], a[:, None])
        log_prob = torch.logsumexp(F.log_softmax(mix[0], -1) + comp, -1)
        clipped_step(opt_c, loss_c, c_params)
        clipped_step(opt_p, -(w * log_prob).mean(), p_params)
        steps[0] += 1
        if steps[0] % c.target_update_period == 0:
            copy_into(t_policy, policy)
            copy_into(t_critic, critic)
        return loss_c.item()

    return update, nn.ModuleList([policy, critic])


def minimal_cql(c, seed: int = 0):
    """CQL(H) on SAC past its cloning phase (the bench sets ``bc_steps=0``), fixed alpha'."""
    torch.manual_seed(seed)
    g = torch.Generator().manual_seed(seed)
    n = c.num_samples
    policy = relu_mlp(OBS_DIM, c.policy_layers, 2 * ACT_DIM)
    critics = nn.ModuleList([relu_mlp(OBS_DIM + ACT_DIM, c.critic_layers, 1) for _ in range(2)])
    t_critics = frozen(critics)
    log_alpha = nn.Parameter(torch.zeros(()))
    opt_p, opt_c = adam(policy.parameters(), c.policy_lr), adam(critics.parameters(), c.critic_lr)
    opt_alpha = adam([log_alpha], c.alpha_lr)
    p_params = list(policy.parameters())
    target_entropy = -float(ACT_DIM) if c.target_entropy is None else c.target_entropy
    log_uniform = ACT_DIM * math.log(0.5)

    def dist(x):
        mean, log_std = policy(x).chunk(2, -1)
        return mean, log_std.clamp(-20.0, 2.0).exp()

    def sample(mean, std, num: int):
        u = mean + std * torch.randn((num, *mean.shape), generator=g)
        log_det = 2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))
        return torch.tanh(u), gaussian_log_prob(mean, std, u) - log_det.sum(-1)

    def q_both(nets, x, a):
        sa = torch.cat([x.expand(*a.shape[:-1], OBS_DIM), a], -1)
        return torch.stack([nets[0](sa).squeeze(-1), nets[1](sa).squeeze(-1)])

    def update(batch):
        x, a, r, d, nx = tensors(batch)
        mean, std = dist(x)
        with torch.no_grad():
            n_mean, n_std = dist(nx)
            na, _ = sample(n_mean, n_std, 1)
            y = r * c.reward_scale + c.gamma * d * q_both(t_critics, nx, na[0]).amin(0)
            rand_a = torch.rand((n, *a.shape), generator=g) * 2.0 - 1.0
            curr_a, lp_curr = sample(mean, std, n)
            next_a, lp_next = sample(n_mean, n_std, n)
        pi_a, log_pi = sample(mean, std, 1)
        step(opt_alpha, -(log_alpha * (log_pi[0].detach() + target_entropy)).mean())
        alpha = log_alpha.detach().exp()
        step(opt_p, (alpha * log_pi[0] - q_both(critics, x, pi_a[0]).amin(0)).mean(), p_params)
        q_data = q_both(critics, x, a)
        q_rand, q_curr, q_next = (q_both(critics, x, p) for p in (rand_a, curr_a, next_a))
        logits = torch.cat([q_rand - log_uniform, q_next - lp_next, q_curr - lp_curr], 1)
        t = c.cql_temperature
        reg = t * torch.logsumexp(logits / t, 1).mean(-1) - q_data.mean(-1)
        td = (q_data - y).pow(2).mean(1)
        loss = (td + c.cql_weight * reg).sum()
        step(opt_c, loss)
        lerp_into(t_critics, critics, c.tau)
        return loss.item()

    return update, nn.ModuleList([policy, critics, nn.ParameterList([log_alpha])])


MINIMAL = {
    "iql": minimal_iql,
    "crr": minimal_crr,
    "cql": minimal_cql,
    "bc": minimal_bc,
    "bcq": minimal_bcq,
    "d4pg": minimal_d4pg,
    "brac": minimal_brac,
    "rabm": minimal_rabm,
    "dmpo": minimal_dmpo,
}


# ----------------------------------------------------------------------------- d3rlpy


def d3rlpy_buffer(ds):
    """rlu's episodes as one d3rlpy MDPDataset (observation keys concatenated in sorted order;
    each episode's final observation row dropped, its last transition a timeout)."""
    import d3rlpy

    obs = np.concatenate([np.asarray(ds.column(f"observation/{k}")) for k in sorted(OBS)], -1)
    last = np.asarray(ds.column("is_last"))
    return d3rlpy.dataset.MDPDataset(
        observations=obs[~last],
        actions=np.asarray(ds.column("action"))[~last],
        rewards=np.asarray(ds.column("reward"))[~last],
        terminals=np.zeros(int((~last).sum())),
        timeouts=np.roll(last, -1)[~last].astype(float),
    )


def residual_encoder_factory(hidden: int, layers: int):
    """A d3rlpy encoder factory building rlu's residual MLP (the torso of rlu's BC and CRR; with
    an action, the action joins the observation before it, as in rlu's CRR critic)."""
    from d3rlpy.models.encoders import EncoderFactory
    from d3rlpy.models.torch import Encoder, EncoderWithAction

    class ResidualEncoder(Encoder):
        def __init__(self, inp: int):
            super().__init__()
            self.net = ResidualMLP(inp, hidden, layers)

        def forward(self, x):
            return self.net(x)

    class ResidualEncoderWithAction(EncoderWithAction):
        def __init__(self, inp: int):
            super().__init__()
            self.net = ResidualMLP(inp, hidden, layers)

        def forward(self, x, action):
            return self.net(torch.cat([x, action], -1))

    @dataclasses.dataclass()
    class ResidualEncoderFactory(EncoderFactory):
        def create(self, observation_shape):
            return ResidualEncoder(observation_shape[0])

        def create_with_action(self, observation_shape, action_size, discrete_action=False):
            return ResidualEncoderWithAction(observation_shape[0] + action_size)

        @staticmethod
        def get_type() -> str:
            return "rlu_residual_mlp"

    return ResidualEncoderFactory()


def d3rlpy_config(name: str, c, same_network: bool = False):
    """d3rlpy's config of the same algorithm with rlu's widths and constants."""
    import d3rlpy
    from d3rlpy.models.encoders import VectorEncoderFactory

    def mlp(widths):
        return VectorEncoderFactory(hidden_units=list(widths))

    if name == "bc":
        encoder = (residual_encoder_factory(c.hidden_size, c.num_layers) if same_network
                   else VectorEncoderFactory())  # d3rlpy's default: 256-256 ReLU  # fmt: skip
        return d3rlpy.algos.BCConfig(
            batch_size=c.batch_size, learning_rate=c.learning_rate, policy_type="stochastic",
            encoder_factory=encoder,
        )  # fmt: skip
    if name == "bcq":
        target = dict(tau=c.tau) if c.target_update_period == 0 else {}
        if c.target_update_period > 0:
            print("  note: d3rlpy's BCQ has Polyak targets only (tau 0.005); rlu copies every "
                  f"{c.target_update_period} updates (the paper's table)")  # fmt: skip
        return d3rlpy.algos.BCQConfig(
            batch_size=c.batch_size, gamma=c.gamma, actor_learning_rate=c.actor_lr,
            critic_learning_rate=c.critic_lr, imitator_learning_rate=c.vae_lr,
            actor_encoder_factory=mlp(c.actor_layers), critic_encoder_factory=mlp(c.critic_layers),
            imitator_encoder_factory=mlp(c.vae_layers), n_action_samples=c.num_samples,
            lam=c.lmbda, action_flexibility=c.phi, beta=0.5, **target,
        )  # fmt: skip
    if name == "iql":
        return d3rlpy.algos.IQLConfig(
            actor_learning_rate=c.actor_lr, critic_learning_rate=c.critic_lr,
            batch_size=c.batch_size, gamma=c.gamma, tau=c.tau, n_critics=2,
            expectile=c.expectile, weight_temp=c.beta, max_weight=c.max_weight,
            actor_encoder_factory=mlp(c.hidden_layers), critic_encoder_factory=mlp(c.hidden_layers),
            value_encoder_factory=mlp(c.hidden_layers),
        )  # fmt: skip
    if name == "crr":
        widths = [c.hidden_size] * c.num_layers
        if same_network:
            residual = residual_encoder_factory(c.hidden_size, c.num_layers)
            mlp = lambda _widths: residual  # noqa: E731
        return d3rlpy.algos.CRRConfig(
            actor_learning_rate=c.policy_lr, critic_learning_rate=c.critic_lr,
            batch_size=c.batch_size, gamma=c.gamma, beta=c.beta,
            n_action_samples=c.num_advantage_samples, advantage_type=c.baseline,
            weight_type=c.advantage_weight, max_weight=c.ratio_upper_bound,
            target_update_type="hard", target_update_interval=c.target_update_period,
            actor_encoder_factory=mlp(widths), critic_encoder_factory=mlp(widths),
        )  # fmt: skip
    if name == "cql":
        lagrange = c.lagrange_threshold is not None
        return d3rlpy.algos.CQLConfig(
            actor_learning_rate=c.policy_lr, critic_learning_rate=c.critic_lr,
            temp_learning_rate=c.alpha_lr, alpha_learning_rate=c.alpha_lr if lagrange else 0.0,
            alpha_threshold=c.lagrange_threshold if lagrange else 10.0,
            batch_size=c.batch_size, gamma=c.gamma, tau=c.tau, n_critics=2,
            conservative_weight=c.cql_weight, n_action_samples=c.num_samples,
            actor_encoder_factory=mlp(c.policy_layers),
            critic_encoder_factory=mlp(c.critic_layers),
        )  # fmt: skip
    if name == "td3bc":  # the observation scaler is set by the caller, from the data
        return d3rlpy.algos.TD3PlusBCConfig(
            actor_learning_rate=c.actor_lr, critic_learning_rate=c.critic_lr,
            batch_size=c.batch_size, gamma=c.gamma, tau=c.tau, n_critics=2, alpha=c.alpha,
            target_smoothing_sigma=c.policy_noise, target_smoothing_clip=c.noise_clip,
            update_actor_interval=c.policy_freq, actor_encoder_factory=mlp(c.hidden_layers),
            critic_encoder_factory=mlp(c.hidden_layers),
        )  # fmt: skip
    if name == "rebrac":
        return d3rlpy.algos.ReBRACConfig(
            actor_learning_rate=c.actor_lr, critic_learning_rate=c.critic_lr,
            batch_size=c.batch_size, gamma=c.gamma, tau=c.tau, n_critics=2,
            actor_beta=c.actor_bc_coef, critic_beta=c.critic_bc_coef,
            target_smoothing_sigma=c.policy_noise, target_smoothing_clip=c.noise_clip,
            update_actor_interval=c.policy_freq,
            actor_encoder_factory=VectorEncoderFactory(
                hidden_units=list(c.actor_layers), use_layer_norm=c.actor_layer_norm),
            critic_encoder_factory=VectorEncoderFactory(
                hidden_units=list(c.critic_layers), use_layer_norm=c.critic_layer_norm),
        )  # fmt: skip
    return None


def d3rlpy_contestant(name: str, c, buffer, same_network: bool = False) -> Contestant | None:
    config = d3rlpy_config(name, c, same_network)
    if config is None:
        return None
    algo = config.create(device="cpu:0")
    algo.build_with_dataset(buffer)
    size = c.batch_size
    return Contestant(lambda: buffer.sample_transition_batch(size), algo.update)


# ----------------------------------------------------------------------------- the bench


def param_count(modules) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())


def run_agent(label: str, name: str, ds, buffer, args, overrides: dict, same_network=False):
    agent = make_agent(name, OBS, ACTION, "paper", 0, **overrides)
    c, spec = agent.config, agent.batch_spec
    sampler = make_sampler(ds, spec, seed=0)
    contestants = {"rlu": Contestant(sampler.sample, agent.update)}
    notes = {"rlu": f"{name} {dataclasses.asdict(c)}"}
    trainable = {k: m for k, m in agent.modules.items() if not k.startswith("target")}
    sizes = f"rlu {param_count(trainable.values()):,} parameters"
    if name in MINIMAL:
        update, modules = MINIMAL[name](c)
        mini = MinimalSampler(ds, spec.batch_size, spec.n_step, spec.gamma, seed=0)
        contestants["minimal loop"] = Contestant(mini.sample, update)
        sizes += f", minimal loop {param_count([modules]):,}"
    else:
        print(f"\n  {label}: no minimal loop for {name!r} yet (add one to MINIMAL)")
    if buffer is not None:
        d3 = d3rlpy_contestant(name, c, buffer, same_network)
        if d3 is not None:
            contestants["d3rlpy"] = d3
    if args.bf16:
        twin = make_agent(name, OBS, ACTION, "paper", 0, **overrides)
        sampler2 = make_sampler(ds, spec, seed=0)
        contestants["rlu bf16"] = Contestant(sampler2.sample, bf16(twin.update))
    notes["sizes"] = sizes + " (trainable, targets excluded)"
    before = load_line()
    rates = time_contestants(contestants, args.rounds, args.block, args.warmup)
    notes["load"] = f"before {before}; after {load_line()}"
    return report(label, rates, notes)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    names = list(SETTINGS)
    p.add_argument("--agents", nargs="+", default=names, choices=names)
    p.add_argument("--rounds", type=int, default=30, help="interleaved rounds")
    p.add_argument("--block", type=float, default=0.05,
                   help="CPU-seconds of updates per contestant per round")  # fmt: skip
    p.add_argument("--warmup", type=int, default=6)
    p.add_argument("--bf16", action="store_true",
                   help="time rlu under CPU bf16 autocast too (opt-in, other numbers)")  # fmt: skip
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads for all")
    p.add_argument("--no-d3rlpy", action="store_true", help="rlu and the minimal loops only")
    args = p.parse_args(argv)
    sys.stdout.reconfigure(line_buffering=True)
    torch.set_num_threads(args.threads)
    have_d3rlpy = not args.no_d3rlpy
    if have_d3rlpy:
        try:
            import d3rlpy
            import structlog

            structlog.configure(
                wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING)
            )
            print(f"d3rlpy {d3rlpy.__version__}")
        except ImportError:
            have_d3rlpy = False
            print("d3rlpy is not installed here: rlu and the minimal loops only (bench/README.md)")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {args.rounds} rounds "
          f"x {args.block:g} CPU-s per contestant (median update); {load_line()}; "
          f"{cpu_line()}")  # fmt: skip
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        ds = make_data(f"{tmp}/data", episodes=50, length=1000)
        buffer = d3rlpy_buffer(ds) if have_d3rlpy else None
        for name in args.agents:
            if (name, False) not in AGENTS:
                print(f"\nskip {name}: no continuous agent {name!r} in rlu.agents.AGENTS yet "
                      "(it runs here once registered)")  # fmt: skip
                continue
            overrides = SETTINGS[name]
            if name == "crr":
                results["crr (preset)"] = run_agent("crr (preset: mixture, categorical critic; "
                                                    "d3rlpy: plain MLPs, Gaussian, scalar Q)",
                                                    name, ds, buffer, args, overrides)  # fmt: skip
                one = {**overrides, "mixture_components": 1}
                results["crr (same torso)"] = run_agent(
                    "crr (same torso: rlu's residual MLPs in d3rlpy, one Gaussian each; critic "
                    "heads still differ: 21 atoms vs one value)", name, ds, buffer, args, one,
                    same_network=True,
                )  # fmt: skip
            elif name == "bc":
                results["bc (preset)"] = run_agent("bc (preset: 5-component mixture)", name, ds,
                                                   buffer, args, overrides)  # fmt: skip
                one = {**overrides, "mixture_components": 1}
                results["bc (same network)"] = run_agent(
                    "bc (same network: one Gaussian on the residual MLP)", name, ds, buffer,
                    args, one, same_network=True,
                )  # fmt: skip
            else:
                results[name] = run_agent(name, name, ds, buffer, args, overrides)
    summary(results)


if __name__ == "__main__":
    main()
