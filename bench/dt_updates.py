"""rlu's Decision Transformer against d3rlpy's DecisionTransformer and DiscreteDecisionTransformer,
update for update and side by side in speed.

Same maths: both libraries start from the same weights (rlu's, copied into d3rlpy's modules)
and take the same batches (rlu's sampler; windows with no padding and no episode end, the only
ones on which d3rlpy's losses and rlu's agree: d3rlpy averages over padded steps too, and
rlu also leaves out each episode's final step); dropout is 0 in both (the two libraries draw it
from different streams). Each prints its loss per update; the largest difference, and the
largest difference between the two sets of weights after the last update, are printed at the
end. What d3rlpy does otherwise, aligned here so that the arithmetic is the same:

- its blocks' LayerNorms use eps 0.003 (GPT-2 and both DT codes: 1e-5): set to 1e-5;
- its state encoder is a factory's: here one that computes rlu's (continuous: the linear
  state embedding of the normalised features, which d3rlpy is handed already normalised with
  rlu's statistics; Atari: the Nature CNN and its linear layer, d3rlpy's tanh on every embedding
  being the Atari code's);
- its Atari global position embeds the window's last timestep (the DT Atari code and rlu: the
  first): it is handed the first timestep in every slot; its learnt positions are one per step,
  shared by the step's three tokens (the Atari code's and rlu's: one per token), so the check
  holds both at their initial zeros (frozen), the one parameter it leaves out;
- returns to go are handed scaled (rlu: / return_scale) and timesteps clipped; its embedding
  tables hold ``max_timestep + 2`` rows (two ``+ 1`` on the way), so it is built with rlu's
  ``max_timestep - 1``.

Speed: both libraries' update, each on its own kind of batch made ready beforehand (rlu: the
sampler's numpy ``Sequence``; d3rlpy: its ``TorchTrajectoryMiniBatch`` of tensors), at the
presets' sizes with their dropout, interleaved for ``--rounds`` rounds; the median update time
of each and the ratio, with the machine's load.

    .venv-bench/bin/python bench/dt_updates.py --updates 200
    .venv-bench/bin/python bench/dt_updates.py --kind atari --updates 50 --atari-batch 32

d3rlpy lives in the bench venv (bench/README.md). A difference that grows past float rounding
means the two updates are not the same maths.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rlu.agents import make_agent  # noqa: E402
from rlu.data import open_dataset  # noqa: E402
from rlu.data.bundled import bundled_dataset  # noqa: E402
from rlu.data.statistics import dataset_statistics  # noqa: E402
from rlu.data.views import make_sampler  # noqa: E402

CONTROL = "control_suite/cartpole_swingup"


class Joined(nn.Module):
    """d3rlpy's state encoder for the continuous case: rlu's state embedding of the (already
    normalised, sorted-key) features."""

    def __init__(self, features: int, width: int):
        super().__init__()
        self.linear = nn.Linear(features, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.linear(x)


class Frames(nn.Module):
    """d3rlpy's state encoder for Atari: rlu's Nature CNN (uint8-valued HWC frames scaled as rlu
    scales them) and linear layer; d3rlpy adds the tanh."""

    def __init__(self, torso: nn.Module, linear: nn.Linear):
        super().__init__()
        self.torso, self.linear = torso, linear

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.linear(self.torso(x.permute(0, 3, 1, 2).float().mul_(1.0 / 255.0)))


def factory(module_fn):
    """A d3rlpy EncoderFactory that builds ``module_fn()``."""
    from d3rlpy.models import EncoderFactory

    @dataclasses.dataclass()
    class Made(EncoderFactory):
        def create(self, observation_shape):
            return module_fn()

        @staticmethod
        def get_type() -> str:
            return "rlu_dt_bench"

    return Made()


def layer_norm_eps(module: nn.Module, eps: float = 1e-5) -> None:
    for m in module.modules():
        if isinstance(m, nn.LayerNorm):
            m.eps = eps


def copy_blocks(ours, theirs) -> None:
    """rlu's GPT (joint qkv) into d3rlpy's GPT2 (separate q, k, v)."""
    gpt = theirs._gpt2
    with torch.no_grad():
        for a, b in zip(ours.transformer.blocks, gpt._transformer, strict=True):
            w = a.qkv.weight.shape[1]
            for i, lin in enumerate((b._attention._q, b._attention._k, b._attention._v)):
                lin.weight.copy_(a.qkv.weight[i * w : (i + 1) * w])
                lin.bias.copy_(a.qkv.bias[i * w : (i + 1) * w])
            pairs = [(a.proj, b._attention._proj), (a.mlp[0], b._mlp._l1), (a.mlp[2], b._mlp._l2),
                     (a.ln_1, b._layer_norm1), (a.ln_2, b._layer_norm2)]  # fmt: skip
            for x, y in pairs:
                y.load_state_dict(x.state_dict())
        gpt._layer_norm.load_state_dict(ours.transformer.ln_f.state_dict())


def joined(observation: dict) -> np.ndarray:
    return np.concatenate([observation[k] for k in sorted(observation)], -1).astype(np.float32)


def full_windows(sampler, size: int):
    """A batch of ``size`` windows with every step real and no episode end (sampled, filtered)."""
    while True:
        b = sampler.sample()
        ok = np.flatnonzero(b.mask.all(1) & ~b.is_last.any(1))
        if len(ok) >= size:
            pick = ok[:size]
            return type(b)(*(_take(x, pick) for x in b))


def _take(x, rows):
    if x is None:
        return None
    if isinstance(x, dict):
        return {k: v[rows] for k, v in x.items()}
    return x[rows]


# ------------------------------------------------------------------------------ the two setups


def continuous(dropout: float, batch: int, check: bool = False):
    import d3rlpy

    ds = open_dataset(bundled_dataset(CONTROL))
    over = {"dropout": dropout, "batch_size": batch}
    if check:  # the paper's 10,000 warm-up updates would keep the check's steps tiny
        over["warmup_steps"] = 20
    agent = make_agent("dt", ds.schema.observation, ds.schema.action, "paper", **over)
    stats = dataset_statistics(ds, agent.batch_spec.statistics)
    agent.set_statistics(stats)
    c = agent.settings
    width = c.hidden_size
    features = sum(s.size for s in ds.schema.observation.values())
    config = d3rlpy.algos.DecisionTransformerConfig(
        context_size=c.context_length, max_timestep=c.max_timestep - 1, batch_size=c.batch_size,
        learning_rate=c.learning_rate, num_heads=c.num_heads, num_layers=c.num_layers,
        attn_dropout=dropout, resid_dropout=dropout, embed_dropout=dropout,
        activation_type="relu", encoder_factory=factory(lambda: Joined(features, width)),
        optim_factory=d3rlpy.optimizers.AdamWFactory(
            weight_decay=c.weight_decay, clip_grad_norm=c.max_grad_norm,
            lr_scheduler_factory=d3rlpy.optimizers.WarmupSchedulerFactory(c.warmup_steps)),
    )  # fmt: skip
    algo = config.create(device="cpu:0")
    algo.create_impl((features,), ds.schema.action.size)
    t = algo.impl.modules.transformer
    m = agent.model
    with torch.no_grad():
        t._encoder.linear.load_state_dict(m.embed_state.state_dict())
        t._rtg_embed.load_state_dict(m.embed_return.state_dict())
        t._action_embed.load_state_dict(m.embed_action.state_dict())
        t._position_encoding._embed.load_state_dict(m.embed_timestep.state_dict())
        t._embed_ln.load_state_dict(m.embed_ln.state_dict())
        t._output.load_state_dict(m.predict_action.state_dict())
    copy_blocks(m, t)
    layer_norm_eps(t)
    mean, std = joined(stats.observation_mean), joined(stats.observation_std)

    def convert(b):
        from d3rlpy.torch_utility import TorchTrajectoryMiniBatch

        obs = (joined(b.observation) - mean) / (std + 1e-6)
        n, k = b.mask.shape
        return TorchTrajectoryMiniBatch(
            observations=torch.from_numpy(obs.astype(np.float32)),
            actions=torch.from_numpy(b.action.astype(np.float32)),
            rewards=torch.from_numpy(b.reward[..., None].astype(np.float32)),
            returns_to_go=torch.from_numpy(b.return_to_go[..., None] / c.return_scale),
            terminals=torch.zeros(n, k, 1),
            timesteps=torch.from_numpy(np.minimum(b.timestep, c.max_timestep)),
            masks=torch.ones(n, k), device="cpu:0",
        )  # fmt: skip

    def weights_gap() -> float:
        first = t._gpt2._transformer[0]
        pairs = [(m.embed_state.weight, t._encoder.linear.weight),
                 (m.embed_timestep.weight, t._position_encoding._embed.weight),
                 (m.predict_action.weight, t._output.weight),
                 (m.transformer.blocks[0].mlp[0].weight, first._mlp._l1.weight)]  # fmt: skip
        return max(float((a - b).detach().abs().max()) for a, b in pairs)

    return ds, agent, algo, convert, weights_gap


def atari(dropout: float, batch: int, check: bool = False):
    import d3rlpy

    from rlu.data.store import Schema
    from rlu.data.synthetic import write_synthetic
    from rlu.tasks import get_task
    from rlu.training.prepare import dataset_specs

    root = Path(os.environ.get("TMPDIR", "/tmp")) / "rlu_dt_bench_atari"
    if not (root / "manifest.json").exists():  # random frames: the arithmetic is the same
        write_synthetic(root, Schema.for_task(get_task("atari/Pong")), 12, 200, seed=0)
    ds = open_dataset(root)
    obs_spec, action_spec = dataset_specs(ds)
    over = {"atari.dropout": dropout, "atari.batch_size": batch, "atari.target_return": 20.0}
    agent = make_agent("dt", obs_spec, action_spec, "paper", **over)
    c = agent.settings
    m = agent.model
    torso, linear = m.embed_state[0], m.embed_state[1]
    config = d3rlpy.algos.DiscreteDecisionTransformerConfig(
        context_size=c.context_length, max_timestep=c.max_timestep - 1, batch_size=c.batch_size,
        learning_rate=c.learning_rate, num_heads=c.num_heads, num_layers=c.num_layers,
        attn_dropout=dropout, resid_dropout=dropout, embed_dropout=dropout,
        activation_type="gelu", embed_activation_type="tanh",
        warmup_tokens=c.warmup_tokens, final_tokens=c.final_tokens,
        encoder_factory=factory(lambda: Frames(_copy(torso), _copy(linear))),
        optim_factory=d3rlpy.optimizers.GPTAdamWFactory(
            betas=c.betas, weight_decay=c.weight_decay, clip_grad_norm=c.max_grad_norm),
    )  # fmt: skip
    algo = config.create(device="cpu:0")
    algo.create_impl(obs_spec.shape, action_spec.num_values)
    t = algo.impl.modules.transformer
    with torch.no_grad():
        t._encoder.load_state_dict(Frames(torso, linear).state_dict())
        t._rtg_embed.load_state_dict(m.embed_return[0].state_dict())
        t._action_embed.load_state_dict(m.embed_action[0].state_dict())
        t._output.load_state_dict(m.head.state_dict())
        pe = t._position_encoding
        pe._global_position_embedding.weight.copy_(m.global_position)
        pe._block_position_embedding._parameter.copy_(m.position[None])
    copy_blocks(m, t)
    layer_norm_eps(t)
    if check:  # d3rlpy: one learnt position per step, the Atari code and rlu: one per token
        m.position.requires_grad_(False)
        pe._block_position_embedding._parameter.requires_grad_(False)

    def convert(b):
        from d3rlpy.torch_utility import TorchTrajectoryMiniBatch

        n, k = b.mask.shape
        first = np.minimum(b.timestep[:, :1], c.max_timestep)  # d3rlpy reads the last slot
        return TorchTrajectoryMiniBatch(
            observations=torch.from_numpy(b.observation).float(),
            actions=torch.from_numpy(b.action[..., None].astype(np.float32)),
            rewards=torch.from_numpy(b.reward[..., None].astype(np.float32)),
            returns_to_go=torch.from_numpy(b.return_to_go[..., None] / c.return_scale),
            terminals=torch.zeros(n, k, 1),
            timesteps=torch.from_numpy(np.repeat(first, k, 1)),
            masks=torch.ones(n, k), device="cpu:0",
        )  # fmt: skip

    def weights_gap() -> float:
        first = t._gpt2._transformer[0]
        pairs = [(m.head.weight, t._output.weight),
                 (m.global_position, pe._global_position_embedding.weight),
                 (m.embed_state[1].weight, t._encoder.linear.weight),
                 (m.transformer.blocks[0].mlp[0].weight, first._mlp._l1.weight)]  # fmt: skip
        return max(float((a - b).detach().abs().max()) for a, b in pairs)

    return ds, agent, algo, convert, weights_gap


def _copy(module: nn.Module) -> nn.Module:
    import copy

    return copy.deepcopy(module)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--kind", choices=("continuous", "atari", "both"), default="both")
    p.add_argument("--updates", type=int, default=200, help="updates of the same-maths check")
    p.add_argument("--every", type=int, default=50, help="print every N updates")
    p.add_argument("--rounds", type=int, default=30, help="interleaved rounds of the speed check")
    p.add_argument("--atari-batch", type=int, default=128, help="Atari windows per update")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    try:
        import d3rlpy  # noqa: F401
        import structlog
    except ImportError:
        sys.exit("d3rlpy is not installed here: run this in the bench venv (bench/README.md)")
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    kinds = ("continuous", "atari") if args.kind == "both" else (args.kind,)
    load = os.getloadavg()[0]
    print(f"torch {torch.__version__}, 1 thread, load {load:.2f} on {os.cpu_count()} cores")
    for kind in kinds:
        make = continuous if kind == "continuous" else atari
        size = 64 if kind == "continuous" else args.atari_batch
        same_maths(kind, make, size, args)
        speed(kind, make, size, args.rounds)


def same_maths(kind, make, size, args) -> None:
    ds, agent, algo, convert, weights_gap = make(0.0, size, check=True)
    sampler = make_sampler(ds, dataclasses.replace(agent.batch_spec, batch_size=4 * size), seed=0)
    warm = "warm-up 20 updates" if kind == "continuous" else "the paper's warm-up"
    print(f"\n{kind}: same weights, same batches, dropout 0, {warm}, {args.updates} updates")
    worst = 0.0
    for step in range(1, args.updates + 1):
        b = full_windows(sampler, size)
        ours = agent.update(b)["actor/loss"]
        theirs = algo.impl.update(convert(b), step - 1)["loss"]
        worst = max(worst, abs(ours - theirs) / max(abs(ours), 1e-12))
        if step % args.every == 0 or step <= 2:
            rel = abs(ours - theirs) / abs(ours)
            print(f"update {step}: rlu {ours:.7f} | d3rlpy {theirs:.7f} | rel. diff {rel:.1e}")
    print(f"{kind}: largest relative loss difference {worst:.1e} over {args.updates} updates; "
          f"largest weight difference after them {weights_gap():.1e}")  # fmt: skip


def speed(kind, make, size, rounds) -> None:
    ds, agent, algo, convert, _ = make(0.1, size)
    sampler = make_sampler(ds, agent.batch_spec, seed=1)
    ours_t, theirs_t = [], []
    for r in range(rounds + 2):  # two warm-up rounds
        b = sampler.sample()
        tb = convert(full_windows(sampler, size))
        t0 = time.perf_counter()
        agent.update(b)
        t1 = time.perf_counter()
        algo.impl.update(tb, r)
        t2 = time.perf_counter()
        if r >= 2:
            ours_t.append(t1 - t0)
            theirs_t.append(t2 - t1)
    a, b = statistics.median(ours_t), statistics.median(theirs_t)
    print(f"{kind} speed (batch {size}, K {agent.settings.context_length}, dropout 0.1, "
          f"{rounds} interleaved rounds): rlu {1 / a:.2f} updates/s, d3rlpy {1 / b:.2f} "
          f"updates/s: rlu / d3rlpy {b / a:.2f}x; load {os.getloadavg()[0]:.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
