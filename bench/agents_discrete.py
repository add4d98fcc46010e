"""Updates per second of every discrete (Atari) rlu agent vs a minimal PyTorch loop with the same
maths, and vs d3rlpy for the algorithms both have (CPU, one run, interleaved).

    .venv-bench/bin/python bench/agents_discrete.py                  # batch 32, every agent
    .venv-bench/bin/python bench/agents_discrete.py --batch 256 --agents dqn double_dqn
    .venv/bin/python bench/agents_discrete.py --no-d3rlpy            # without d3rlpy

d3rlpy lives in the bench venv (bench/README.md), never in rlu's dependencies. Data: one rlu
dataset of random 84x84 frames (Atari layout: single frames stored once, stacked by four at sample
time, 6 actions), written with rlu's writer; every contestant samples the same steps its own way:

- rlu: ``make_sampler(dataset, agent.batch_spec)`` and ``agent.update(batch)``, the training
  loop's two calls; agents built by name with ``rlu.agents.make_agent``, paper preset (Nature CNN
  32-64-64, 512 units, Adam epsilon 1e-7, rewards clipped to [-1, 1]) at ``--batch``;
- minimal loop: the frame column read into RAM, stacks gathered by numpy fancy indexing (one
  gather of five frames per transition serves both stacks), and the agent's maths written out
  straight on plain modules of the same sizes (read from the rlu agent's config), fused Adam;
- d3rlpy 2.8.1: its replay buffer over the same episodes (single frames, its
  ``FrameStackTransitionPicker(4)``) and ``algo.update``, with the same Nature CNN, learning
  rate, Adam epsilon, discount, reward clipping and target period. Pairs: ``dqn`` (double-Q off)
  with ``DQN``, ``double_dqn`` (rlu's dqn preset) with ``DoubleDQN``, ``bc`` with ``DiscreteBC``
  (beta 0: no logit penalty, as rlu's), ``bcq`` with ``DiscreteBCQ`` (d3rlpy's imitation head
  sits on the shared 512 features, rlu's has its own 512-unit layer, as Fujimoto et al.'s),
  ``cql`` with ``DiscreteCQL`` (d3rlpy runs the Q-network on the observations twice with
  gradients, rlu once), ``iqn`` with d3rlpy's DQN on its ``IQNQFunctionFactory`` (the same
  quantile count and embedding; its target runs the target network twice, rlu's once). ``rem``
  and ``dopamine_dqn`` (the Atari data's behaviour agent: TF1's centered RMSProp, whose epsilon
  sits inside the square root, unlike torch's and d3rlpy's RMSprop) have no d3rlpy counterpart.

Timing (bench/agents_timing.py): "sample + update" and "update only", updates per CPU-second of
the process (and wall), one over the median time of an update in many short interleaved rounds,
one torch thread unless ``--threads``.
d3rlpy's sampler casts frames to float32 itself, so its "update only" starts from float32 arrays.
"""

from __future__ import annotations

import argparse
import copy
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
from rlu.types import ArraySpec, DiscreteSpec  # noqa: E402

FRAME = ArraySpec((84, 84), "uint8")
OBS = ArraySpec((84, 84, 4), "uint8")
NUM_ACTIONS = 6
ACTION = DiscreteSpec((), "int64", NUM_ACTIONS)
# bench name -> (rlu agent, overrides on its paper preset)
AGENT_SETTINGS: dict[str, tuple[str, dict]] = {
    "bc": ("bc", {}),
    "dqn": ("dqn", {"double_q": False}),
    "double_dqn": ("dqn", {}),
    "bcq": ("bcq", {}),
    "cql": ("cql", {}),
    "iqn": ("iqn", {}),
    "rem": ("rem", {}),
    "dopamine_dqn": ("dopamine_dqn", {}),
}


# ----------------------------------------------------------------------------- data


def make_data(path, episodes: int, length: int, seed: int = 0):
    """Random frames (each episode's frames drawn once), random actions and rewards in [-2, 2]
    (so the clip to [-1, 1] acts), an episode in four ending in a terminal state."""
    rng = np.random.default_rng(seed)
    with DatasetWriter(path, Schema(FRAME, ACTION, frame_stack=4), {"source": "bench"}) as w:
        for i in range(episodes):
            frames = rng.integers(0, 256, (length + 1, 84, 84), dtype=np.uint8)
            actions = rng.integers(0, NUM_ACTIONS, length).astype(np.int64)
            rewards = rng.uniform(-2, 2, length).astype(np.float32)
            w.append(make_episode(frames, actions, rewards, terminal=i % 4 == 0))
    return open_dataset(path)


class MinimalSampler:
    """Frames in RAM; one (B, 5, 84, 84) gather per batch gives both stacks (NCHW views)."""

    def __init__(self, ds, batch: int, clip: float, seed: int = 0):
        self.frames = np.array(ds.column("observation"))
        start, length = np.asarray(ds.start), np.asarray(ds.length)
        frame_start = np.asarray(ds.frame_start)
        # transitions: every step but a segment's last; the stack of step t starts at frame row
        # frame_start + (t - start) (three zero frames precede each episode)
        self.t = np.concatenate([s + np.arange(n - 1) for s, n in zip(start, length, strict=True)])
        seg = np.repeat(np.arange(len(start)), length - 1)
        self.first = frame_start[seg] + (self.t - start[seg])
        self.action = np.array(ds.column("action"))
        self.reward = np.clip(np.array(ds.column("reward")), -clip, clip)
        self.discount = np.array(ds.column("discount"))
        self.rows = np.arange(5)
        self.batch, self.rng = batch, np.random.default_rng(seed)

    def sample(self):
        i = self.rng.integers(0, len(self.t), self.batch)
        stacks = self.frames[self.first[i][:, None] + self.rows]
        t = self.t[i]
        return stacks[:, :4], self.action[t], self.reward[t], self.discount[t], stacks[:, 1:]


# ----------------------------------------------------------------------------- minimal loops


def nature_cnn(s) -> nn.Sequential:
    layers: list[nn.Module] = []
    c, h = 4, 84
    for out, k, st in zip(s.channels, s.kernel_sizes, s.strides, strict=True):
        layers += [nn.Conv2d(c, out, k, st), nn.ReLU()]
        c, h = out, (h - k) // st + 1
    return nn.Sequential(*layers, nn.Flatten(), nn.Linear(c * h * h, s.hidden_size), nn.ReLU())


def prepare(batch):
    """(observation as channels-last float, action, reward, discount, next observation as NCHW
    float): the gradient pass's convolutions run faster channels-last, the no-gradient passes
    as fast on the plain layout, which is one cheap cast away from the gathered frames."""
    o, a, r, d, o2 = (torch.from_numpy(x) for x in batch)
    x = o.contiguous(memory_format=torch.channels_last).float().mul_(1 / 255)
    return x, a, r, d, o2.float().mul_(1 / 255)


def huber(x, delta: float):
    return F.huber_loss(x, torch.zeros_like(x), reduction="none", delta=delta)


class Loop:
    """A network, its target, Adam, hard target copies: what every minimal discrete loop has."""

    def __init__(self, net: nn.Module, c, target: bool = True):
        self.net, self.c = net, c
        self.target = None
        if target:
            self.target = copy.deepcopy(net).requires_grad_(False)
        self.opt = torch.optim.Adam(net.parameters(), lr=c.learning_rate, eps=c.atari.adam_eps,
                                    fused=True)  # fmt: skip
        self.steps = 0

    def learn(self, loss) -> float:
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.steps += 1
        if self.target is not None and self.steps % self.c.atari.target_update_period == 0:
            with torch.no_grad():
                torch._foreach_copy_(list(self.target.parameters()), list(self.net.parameters()))
        return loss.item()


def q_net(s, out: int) -> nn.Sequential:
    return nn.Sequential(nature_cnn(s), nn.Linear(s.hidden_size, out))


def minimal_q(c, kind: str):
    """DQN (``kind`` 'dqn'), double DQN ('double') or CQL(H) on double DQN ('cql')."""
    torch.manual_seed(0)
    s = c.atari
    loop = Loop(q_net(s, NUM_ACTIONS), c)
    gamma = s.gamma**s.n_step

    def update(batch):
        x, a, r, d, x2 = prepare(batch)
        q = loop.net(x)
        q_taken = q.gather(1, a[:, None]).squeeze(1)
        with torch.no_grad():
            q_next = loop.target(x2)
            if kind == "dqn":
                v = q_next.max(1).values
            else:
                v = q_next.gather(1, loop.net(x2).argmax(1, keepdim=True)).squeeze(1)
            y = r + gamma * d * v
        loss = huber(y - q_taken, s.huber_delta).mean()
        if kind == "cql":
            loss = loss + c.alpha * (torch.logsumexp(q, 1) - q_taken).mean()
        return loop.learn(loss)

    return update, loop.net


def minimal_bc(c):
    torch.manual_seed(0)
    loop = Loop(q_net(c.atari, NUM_ACTIONS), c, target=False)

    def update(batch):
        x, a, *_ = prepare(batch)
        return loop.learn(F.cross_entropy(loop.net(x), a))

    return update, loop.net


def minimal_bcq(c):
    torch.manual_seed(0)
    s = c.atari

    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            self.torso = nature_cnn(s)[:-2]  # the convolutions and the flatten
            size = self.torso(torch.zeros(1, 4, 84, 84)).shape[1]
            self.q = nn.Sequential(nn.Linear(size, s.hidden_size), nn.ReLU(),
                                   nn.Linear(s.hidden_size, NUM_ACTIONS))  # fmt: skip
            self.pi = nn.Sequential(nn.Linear(size, s.hidden_size), nn.ReLU(),
                                    nn.Linear(s.hidden_size, NUM_ACTIONS))  # fmt: skip

        def forward(self, x):
            f = self.torso(x)
            return self.q(f), self.pi(f)

    loop = Loop(Net(), c)
    gamma, log_threshold = s.gamma**s.n_step, math.log(c.threshold)

    def update(batch):
        x, a, r, d, x2 = prepare(batch)
        q_all, logits = loop.net(x)
        q = q_all.gather(1, a[:, None]).squeeze(1)
        with torch.no_grad():
            q2, logits2 = loop.net(x2)
            allowed = logits2 - logits2.max(1, keepdim=True).values >= log_threshold
            best = q2.masked_fill(~allowed, float("-inf")).argmax(1, keepdim=True)
            y = r + gamma * d * loop.target(x2)[0].gather(1, best).squeeze(1)
        loss = (huber(y - q, s.huber_delta).mean() + F.cross_entropy(logits, a)
                + c.logit_penalty * logits.pow(2).mean())  # fmt: skip
        return loop.learn(loss)

    return update, loop.net


def minimal_iqn(c):
    torch.manual_seed(0)
    s, n, e = c.atari, c.num_tau_samples, c.embedding_size
    g = torch.Generator().manual_seed(0)

    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            self.torso = nature_cnn(s)[:-2]
            size = self.torso(torch.zeros(1, 4, 84, 84)).shape[1]
            self.tau = nn.Linear(e, size)
            self.head = nn.Sequential(nn.Linear(size, s.hidden_size), nn.ReLU(),
                                      nn.Linear(s.hidden_size, NUM_ACTIONS))  # fmt: skip
            self.register_buffer("i", torch.arange(e, dtype=torch.float32) * math.pi)

        def forward(self, x, taus):
            phi = F.relu(self.tau(torch.cos(taus[..., None] * self.i)))
            return self.head(self.torso(x)[:, None, :] * phi)  # (B, N, A)

    loop = Loop(Net(), c)
    gamma = s.gamma**s.n_step

    def update(batch):
        x, a, r, d, x2 = prepare(batch)
        b = a.shape[0]
        taus = torch.rand(b, n, generator=g)
        z = loop.net(x, taus).gather(2, a[:, None, None].expand(b, n, 1)).squeeze(2)
        with torch.no_grad():
            z2 = loop.target(x2, torch.rand(b, n, generator=g))
            best = z2.mean(1).argmax(1)
            y = r[:, None] + gamma * d[:, None] * z2.gather(2, best[:, None, None].expand(b, n, 1)
                                                            ).squeeze(2)  # fmt: skip
        u = y[:, None, :] - z[:, :, None]
        w = (taus[:, :, None] - (u.detach() < 0).float()).abs()
        loss = (w * huber(u, c.kappa) / c.kappa).mean(2).sum(1).mean()
        return loop.learn(loss)

    return update, loop.net


def minimal_rem(c):
    torch.manual_seed(0)
    s, k = c.atari, c.num_heads
    loop = Loop(q_net(s, NUM_ACTIONS * k), c)
    g = torch.Generator().manual_seed(0)
    gamma = s.gamma**s.n_step

    def update(batch):
        x, a, r, d, x2 = prepare(batch)
        w = torch.rand(k, generator=g)
        w = w / w.sum()
        q = (loop.net(x).view(-1, k, NUM_ACTIONS) * w[:, None]).sum(1)
        q_taken = q.gather(1, a[:, None]).squeeze(1)
        with torch.no_grad():
            q2 = (loop.target(x2).view(-1, k, NUM_ACTIONS) * w[:, None]).sum(1)
            y = r + gamma * d * q2.max(1).values
        return loop.learn(huber(y - q_taken, s.huber_delta).mean())

    return update, loop.net


def minimal_dopamine_dqn(c):
    """Dopamine's DQN (the Atari data's behaviour agent): DQN's loss without double Q, stepped by
    TF1's centered RMSProp written out with foreach ops (the mean square started at 1, epsilon
    inside the square root, plain momentum), hard target copies."""
    torch.manual_seed(0)
    s = c.atari
    net = q_net(s, NUM_ACTIONS)
    target = copy.deepcopy(net).requires_grad_(False)
    params = list(net.parameters())
    ms = [torch.ones_like(p) for p in params]
    mg, mom = [torch.zeros_like(p) for p in params], [torch.zeros_like(p) for p in params]
    rate, gamma, steps = 1.0 - c.rmsprop_decay, s.gamma**s.n_step, [0]

    def update(batch):
        x, a, r, d, x2 = prepare(batch)
        q_taken = net(x).gather(1, a[:, None]).squeeze(1)
        with torch.no_grad():
            y = r + gamma * d * target(x2).max(1).values
        loss = huber(y - q_taken, s.huber_delta).mean()
        for p in params:
            p.grad = None
        loss.backward()
        with torch.no_grad():
            grads = [p.grad for p in params]
            torch._foreach_lerp_(ms, torch._foreach_mul(grads, grads), rate)
            torch._foreach_lerp_(mg, grads, rate)
            root = torch._foreach_addcmul(ms, mg, mg, value=-1.0)
            torch._foreach_add_(root, c.rmsprop_epsilon)
            torch._foreach_sqrt_(root)
            torch._foreach_mul_(mom, c.rmsprop_momentum)
            torch._foreach_addcdiv_(mom, grads, root, value=c.learning_rate)
            torch._foreach_sub_(params, mom)
        steps[0] += 1
        if steps[0] % s.target_update_period == 0:
            with torch.no_grad():
                torch._foreach_copy_(list(target.parameters()), params)
        return loss.item()

    return update, net


MINIMAL = {
    "bc": minimal_bc,
    "dqn": lambda c: minimal_q(c, "dqn"),
    "double_dqn": lambda c: minimal_q(c, "double"),
    "cql": lambda c: minimal_q(c, "cql"),
    "bcq": minimal_bcq,
    "iqn": minimal_iqn,
    "rem": minimal_rem,
    "dopamine_dqn": minimal_dopamine_dqn,
}


# ----------------------------------------------------------------------------- d3rlpy


def d3rlpy_buffer(ds):
    """rlu's episodes as d3rlpy episodes of single frames (T, 1, 84, 84), stacked by its
    FrameStackTransitionPicker: a terminal episode keeps its T acting rows (d3rlpy bootstraps
    nothing after a terminal), a truncated one its final observation too."""
    from d3rlpy.constants import ActionSpace
    from d3rlpy.dataset import Episode, FrameStackTransitionPicker, InfiniteBuffer, ReplayBuffer

    episodes = []
    for seg in ds.segments():
        terminated = bool(seg.is_terminal[-1])
        rows = len(seg.action) - 1 if terminated else len(seg.action)
        obs = seg.observation[:, None]
        episodes.append(Episode(obs[:rows], seg.action[:rows].reshape(rows, 1),
                                seg.reward[:rows].astype(np.float32).reshape(rows, 1),
                                terminated))  # fmt: skip
    return ReplayBuffer(
        InfiniteBuffer(), episodes=episodes, transition_picker=FrameStackTransitionPicker(4),
        action_space=ActionSpace.DISCRETE, action_size=NUM_ACTIONS,
    )  # fmt: skip


def d3rlpy_iqn_same_network(c):
    """d3rlpy's DQN on an IQN with rlu's (Dopamine's, the IQN paper's) network: the tau
    embedding multiplies the flat convolution features (3136), then the 512-unit layer and the
    action layer run per state and quantile. d3rlpy's own IQN multiplies its encoder's 512
    features and runs one linear layer per quantile: far less arithmetic."""
    import d3rlpy
    from d3rlpy.models.encoders import EncoderFactory
    from d3rlpy.models.q_functions import IQNQFunctionFactory
    from d3rlpy.models.torch import Encoder

    s = c.atari

    class Convolutions(Encoder):
        def __init__(self):
            super().__init__()
            self.net = nature_cnn(s)[:-2]

        def forward(self, x):
            return self.net(x)

    @dataclasses.dataclass()
    class ConvolutionsFactory(EncoderFactory):
        def create(self, observation_shape):
            return Convolutions()

        @staticmethod
        def get_type() -> str:
            return "rlu_nature_convolutions"

    @dataclasses.dataclass()
    class DopamineIQNFactory(IQNQFunctionFactory):
        def create_discrete(self, encoder, hidden_size, action_size):
            q_func, forwarder = super().create_discrete(encoder, hidden_size, action_size)
            q_func._fc = nn.Sequential(nn.Linear(hidden_size, s.hidden_size), nn.ReLU(),
                                       nn.Linear(s.hidden_size, action_size))  # fmt: skip
            return q_func, forwarder

        @staticmethod
        def get_type() -> str:
            return "rlu_dopamine_iqn"

    iqn = DopamineIQNFactory(n_quantiles=c.num_tau_samples,
                             n_greedy_quantiles=c.num_quantile_samples,
                             embed_size=c.embedding_size)  # fmt: skip
    return d3rlpy.algos.DQNConfig(
        batch_size=s.batch_size, learning_rate=c.learning_rate, gamma=s.gamma,
        optim_factory=d3rlpy.optimizers.AdamFactory(eps=s.adam_eps),
        encoder_factory=ConvolutionsFactory(), q_func_factory=iqn,
        observation_scaler=d3rlpy.preprocessing.PixelObservationScaler(),
        reward_scaler=d3rlpy.preprocessing.ClipRewardScaler(-s.reward_clip, s.reward_clip),
        target_update_interval=s.target_update_period,
    )  # fmt: skip


def d3rlpy_algo(bench_name: str, c):
    import d3rlpy
    from d3rlpy.models.encoders import PixelEncoderFactory
    from d3rlpy.models.q_functions import IQNQFunctionFactory

    s = c.atari
    common = dict(
        batch_size=s.batch_size,
        learning_rate=c.learning_rate,
        optim_factory=d3rlpy.optimizers.AdamFactory(eps=s.adam_eps),
        encoder_factory=PixelEncoderFactory(
            filters=[list(f) for f in zip(s.channels, s.kernel_sizes, s.strides, strict=True)],
            feature_size=s.hidden_size,
        ),
        observation_scaler=d3rlpy.preprocessing.PixelObservationScaler(),
    )
    if bench_name == "bc":
        return d3rlpy.algos.DiscreteBCConfig(beta=0.0, **common)
    q = dict(gamma=s.gamma, target_update_interval=s.target_update_period,
             reward_scaler=d3rlpy.preprocessing.ClipRewardScaler(-s.reward_clip, s.reward_clip),
             **common)  # fmt: skip
    if bench_name == "dqn":
        return d3rlpy.algos.DQNConfig(**q)
    if bench_name == "double_dqn":
        return d3rlpy.algos.DoubleDQNConfig(**q)
    if bench_name == "bcq":
        return d3rlpy.algos.DiscreteBCQConfig(action_flexibility=c.threshold,
                                              beta=c.logit_penalty, **q)  # fmt: skip
    if bench_name == "cql":
        return d3rlpy.algos.DiscreteCQLConfig(alpha=c.alpha, **q)
    if bench_name == "iqn":
        iqn = IQNQFunctionFactory(n_quantiles=c.num_tau_samples,
                                  n_greedy_quantiles=c.num_quantile_samples,
                                  embed_size=c.embedding_size)  # fmt: skip
        return d3rlpy.algos.DQNConfig(q_func_factory=iqn, **q)
    return None


# ----------------------------------------------------------------------------- the bench


def param_count(module) -> int:
    return sum(p.numel() for p in module.parameters())


def run_agent(bench_name: str, ds, buffer, args):
    name, overrides = AGENT_SETTINGS[bench_name]
    overrides = {**overrides, "atari.batch_size": args.batch}
    agent = make_agent(name, OBS, ACTION, "paper", 0, **overrides)
    c = agent.config
    sampler = make_sampler(ds, agent.batch_spec, seed=0)
    contestants = {"rlu": Contestant(sampler.sample, agent.update)}
    update, net = MINIMAL[bench_name](c)
    mini = MinimalSampler(ds, args.batch, c.atari.reward_clip, seed=0)
    contestants["minimal loop"] = Contestant(mini.sample, update)
    notes = {
        "rlu": f"{name} {dataclasses.asdict(c)}",
        "sizes": f"rlu {param_count(agent.network):,} parameters, minimal loop "
                 f"{param_count(net):,}",
    }  # fmt: skip
    if buffer is not None:
        configs = {"d3rlpy": d3rlpy_algo(bench_name, c)}
        if bench_name == "iqn":
            configs["d3rlpy same net"] = d3rlpy_iqn_same_network(c)
            notes["d3rlpy"] = "DQN + its IQNQFunctionFactory (tau embedding on 512 features)"
            notes["d3rlpy same net"] = "DQN + IQN on rlu's network (bench's DopamineIQNFactory)"
        for label, config in configs.items():
            if config is None:
                continue
            algo = config.create(device="cpu:0")
            algo.build_with_dataset(buffer)
            contestants[label] = Contestant(
                lambda: buffer.sample_transition_batch(args.batch), algo.update
            )
            notes.setdefault(label, type(config).__name__.removesuffix("Config"))
            if label == "d3rlpy same net":
                notes["sizes"] += f", d3rlpy same net {param_count(algo.impl.q_function):,}"
    if args.bf16:
        twin = make_agent(name, OBS, ACTION, "paper", 0, **overrides)
        sampler2 = make_sampler(ds, twin.batch_spec, seed=0)
        contestants["rlu bf16"] = Contestant(sampler2.sample, bf16(twin.update))
    before = load_line()
    rates = time_contestants(contestants, args.rounds, args.block, args.warmup)
    notes["load"] = f"before {before}; after {load_line()}"
    return report(f"{bench_name} (batch {args.batch})", rates, notes)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    names = list(AGENT_SETTINGS)
    p.add_argument("--agents", nargs="+", default=names, choices=names)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--rounds", type=int, default=30, help="interleaved rounds")
    p.add_argument("--block", type=float, default=0.05,
                   help="CPU-seconds of updates per contestant per round")  # fmt: skip
    p.add_argument("--warmup", type=int, default=4)
    p.add_argument("--bf16", action="store_true",
                   help="time rlu under CPU bf16 autocast too (opt-in, other numbers)")  # fmt: skip
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads for all")
    p.add_argument("--episodes", type=int, default=20, help="1000-step episodes of data")
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
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), batch {args.batch}, "
          f"{args.rounds} rounds x {args.block:g} CPU-s per contestant (median update); "
          f"{load_line()}; {cpu_line()}")  # fmt: skip
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        ds = make_data(f"{tmp}/data", args.episodes, 1000)
        buffer = d3rlpy_buffer(ds) if have_d3rlpy else None
        for bench_name in args.agents:
            if (AGENT_SETTINGS[bench_name][0], True) not in AGENTS:
                print(f"\nskip {bench_name}: not in rlu.agents.AGENTS")
                continue
            results[bench_name] = run_agent(bench_name, ds, buffer, args)
    summary(results)


if __name__ == "__main__":
    main()
