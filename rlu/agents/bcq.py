"""Continuous BCQ (Fujimoto, Meger and Precup 2019; paper appendix A.1, "BCQ").

The paper uses "the exact same network architecture and algorithm" as the original
(github.com/sfujim/BCQ, ``continuous_BCQ/BCQ.py``): a conditional VAE of the behaviour policy
(encoder and decoder 750-750, latent 2 x action dims, decoder latents clipped to [-0.5, 0.5]),
a perturbation network (400-300) that moves each VAE action by at most phi = 0.05, twin
critics (400-300) with the soft clipped double-Q target lambda min + (1 - lambda) max,
lambda = 0.75, the target maximising over 10 sampled actions, Adam 1e-3 everywhere; batch 1024
(the paper's batch, not the original's 100). Targets: the paper's table gives every continuous
agent hard target copies every 100 updates (``paper`` preset); the original's Polyak averaging
(tau = 0.005) is ``target_update_period=0``.

Choices: dict observations go through ``networks.Encoder`` (each network its own, so camera
images get one ResNet per network); actions live in [-1, 1]. ``act(greedy=True)`` scores
``num_samples`` perturbed VAE actions with Q1 and returns the best (as the original's
``select_action``) with latents from a generator seeded with 0 on every call, so it is a
deterministic function of the parameters and the observation; ``greedy=False`` draws from
the agent's own generator.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents import networks as nets
from rlu.agents.losses import vae_loss
from rlu.files import (
    BATCH,
    FRACTION,
    LAYERS,
    LEARNING_RATE,
    MAX_STEPS,
    STEPS,
    WIDTH,
    Checked,
    bounds,
)
from rlu.seeds import stream_seed
from rlu.types import ActionSpec, BatchSpec, Observation, ObservationSpec, RluError, Transition


@dataclass(frozen=True)
class BCQConfig(Checked):
    actor_layers: tuple[int, ...] = field(default=(400, 300), metadata=LAYERS)
    """Perturbation network hidden sizes."""
    critic_layers: tuple[int, ...] = field(default=(400, 300), metadata=LAYERS)
    """Hidden sizes of each of the twin critics."""
    vae_layers: tuple[int, ...] = field(default=(750, 750), metadata=LAYERS)
    """Hidden sizes of the VAE encoder and of its decoder."""
    torso_hidden: int = field(default=64, metadata=WIDTH)
    """Camera ResNet embedding size."""
    phi: float = field(default=0.05, metadata=bounds(min=0.0, max=2.0))
    """Largest perturbation, in units of the action range's half-width."""
    lmbda: float = field(default=0.75, metadata=FRACTION)
    """Weight of the min in the soft clipped double-Q target."""
    num_samples: int = field(default=10, metadata=bounds(min=1, max=10_000))
    """VAE actions sampled per next state (target) and per state (acting)."""
    cpu_slice_rows: int = field(default=640, metadata=bounds(min=0, max=1 << 30))
    """On a CPU, the target pass (``num_samples`` x batch rows through the VAE decoder, the
    perturbation network and both target critics, no gradients) runs in slices of this many
    rows, so that one slice's activations stay in the core's cache: the same values up to float
    rounding, the whole update 1.16x faster at the paper's widths and batch 256 (docs/agents.md).
    0, or a GPU: one pass over all rows."""
    gamma: float = field(default=0.99, metadata=FRACTION)
    """Discount."""
    target_update_period: int = field(default=100, metadata=bounds(min=0, max=MAX_STEPS))
    """Updates between hard copies into the target networks (the paper's table, shared by its
    continuous agents); 0: Polyak averaging with ``tau`` every update (the original BCQ)."""
    tau: float = field(default=0.005, metadata=bounds(gt=0.0, max=1.0))
    """Polyak rate of the target networks when ``target_update_period`` is 0."""
    actor_lr: float = field(default=1e-3, metadata=LEARNING_RATE)
    """Adam learning rate of the perturbation network."""
    critic_lr: float = field(default=1e-3, metadata=LEARNING_RATE)
    """Adam learning rate of the critics."""
    vae_lr: float = field(default=1e-3, metadata=LEARNING_RATE)
    """Adam learning rate of the VAE."""
    batch_size: int = field(default=1024, metadata=BATCH)
    """Transitions per update."""
    num_steps: int = field(default=1_000_000, metadata=STEPS)
    """Learner steps of a full run: what ``rlu train`` runs when no --steps is given. The paper
    states no budget for the continuous baselines; 1M is rlu's choice."""

    def __post_init__(self) -> None:
        super().__post_init__()
        common.slice_rows("BCQ", self.cpu_slice_rows)


Config = BCQConfig
PRESETS = {
    "paper": BCQConfig(),
    "small": BCQConfig(actor_layers=(256, 256), critic_layers=(256, 256),
                       vae_layers=(256, 256), batch_size=256, num_steps=20_000,
                       target_update_period=0),
}  # fmt: skip
GRID: dict[str, list] = {}  # the paper reports no sweep for continuous BCQ


class VAE(nn.Module):
    def __init__(self, feature_dim: int, action_dim: int, layers: tuple[int, ...]) -> None:
        super().__init__()
        self.latent_dim = 2 * action_dim
        self.encoder = nets.mlp(feature_dim + action_dim, layers, 2 * self.latent_dim)
        self.decoder = nets.mlp(feature_dim + self.latent_dim, layers, action_dim)

    def forward(
        self, s: torch.Tensor, a: torch.Tensor, generator: torch.Generator
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        mean, log_std = self.encoder(torch.cat([s, a], -1)).chunk(2, -1)
        std = log_std.clamp(-4, 15).exp()
        z = mean + std * torch.randn(std.shape, generator=generator, device=std.device)
        return self.decode(s, z=z), mean, std

    def decode(
        self,
        s: torch.Tensor,
        generator: torch.Generator | None = None,
        z: torch.Tensor | None = None,
    ) -> torch.Tensor:
        if z is None:
            if generator is None:  # torch's global generator would make the draws unseeded
                raise RluError("VAE.decode: give z or the generator that draws it (a bug in rlu)")
            z = self.prior_latent(s.shape[0], generator, s.device)
        return torch.tanh(self.decoder(torch.cat([s, z], -1)))

    def prior_latent(
        self, rows: int, generator: torch.Generator, device: torch.device
    ) -> torch.Tensor:
        """Latents for decoding without an action: N(0, 1) clipped to [-0.5, 0.5] (BCQ's)."""
        z = torch.randn((rows, self.latent_dim), generator=generator, device=device)
        return z.clamp(-0.5, 0.5)


class BCQNets(nn.Module):
    """Encoders plus the three networks; one module so targets copy it whole."""

    def __init__(self, observation_spec: ObservationSpec, action_dim: int, c: BCQConfig) -> None:
        super().__init__()
        self.actor_enc = nets.Encoder(observation_spec, c.torso_hidden)
        self.critic_enc = nets.Encoder(observation_spec, c.torso_hidden)
        self.vae_enc = nets.Encoder(observation_spec, c.torso_hidden)
        f = self.actor_enc.output_dim
        self.actor = nets.mlp(f + action_dim, c.actor_layers, action_dim)
        self.q1 = nets.mlp(f + action_dim, c.critic_layers, 1)
        self.q2 = nets.mlp(f + action_dim, c.critic_layers, 1)
        self.vae = VAE(f, action_dim, c.vae_layers)

    def perturb(self, s: torch.Tensor, a: torch.Tensor, phi: float) -> torch.Tensor:
        return (a + phi * torch.tanh(self.actor(torch.cat([s, a], -1)))).clamp(-1.0, 1.0)

    def q(self, s: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        sa = torch.cat([s, a], -1)
        return self.q1(sa).squeeze(-1), self.q2(sa).squeeze(-1)

    def q_first(self, s: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """Q1 alone: what the actor loss and acting read (Q2 would be computed for nothing)."""
        return self.q1(torch.cat([s, a], -1)).squeeze(-1)

    def target_parts(self) -> dict[str, nn.Module]:
        """The parts a target copy is read through (the critic target); the VAE's target copy
        is never read (the original decodes with the online VAE), so targets skip it."""
        return {"actor_enc": self.actor_enc, "actor": self.actor, "critic_enc": self.critic_enc,
                "q1": self.q1, "q2": self.q2}  # fmt: skip


def clipped_double_q(q1: torch.Tensor, q2: torch.Tensor, lmbda: float) -> torch.Tensor:
    """BCQ's soft clipped double-Q: lambda min(q1, q2) + (1 - lambda) max(q1, q2)."""
    return lmbda * torch.minimum(q1, q2) + (1.0 - lmbda) * torch.maximum(q1, q2)


def critic_loss(
    q1: torch.Tensor, q2: torch.Tensor, target: torch.Tensor
) -> tuple[torch.Tensor, common.Metrics]:
    loss = (q1 - target).pow(2).mean() + (q2 - target).pow(2).mean()
    return loss, {"critic/loss": loss, "critic/q_mean": q1.mean()}


class BCQAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: BCQConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.scaler = nets.ActionScaler(action_spec)
        self.batch_spec = BatchSpec(config.batch_size, gamma=config.gamma)
        self.num_steps, self.pretrain_steps = config.num_steps, 0
        self.generator = common.generator(stream_seed(seed, "learner"), self.device)
        with common.seeded(seed):
            self.nets = BCQNets(observation_spec, self.scaler.dim, config).to(self.device)
        self.target = common.frozen_copy(self.nets)
        n = self.nets
        self.actor_params = [*n.actor_enc.parameters(), *n.actor.parameters()]
        self.critic_params = [*n.critic_enc.parameters(), *n.q1.parameters(), *n.q2.parameters()]
        self.vae_params = [*n.vae_enc.parameters(), *n.vae.parameters()]
        self.optimizers = {
            "actor": common.adam(self.actor_params, config.actor_lr),
            "critic": common.adam(self.critic_params, config.critic_lr),
            "vae": common.adam(self.vae_params, config.vae_lr),
        }
        self.modules = {"nets": self.nets, "target": self.target}
        self.generators = {"sample": self.generator}
        # the parts the critic target reads, each copied into (or averaged onto) its target
        self.targets = dict(
            zip(self.target.target_parts().values(), self.nets.target_parts().values(), strict=True)
        )

    def update(self, batch: Transition) -> dict[str, float]:
        c, n, g = self.config, self.nets, self.generator
        b = common.transition(batch, self.scaler, self.device)
        obs, action, batch_size = b.observation, b.action, b.action.shape[0]

        s_vae = n.vae_enc(obs)
        recon, mean, std = n.vae(s_vae, action, g)
        loss_v, metrics = vae_loss(recon, action, mean, std)
        common.sgd_step(self.optimizers["vae"], loss_v)

        with torch.no_grad():
            q_t = self.next_value(b.next_observation).reshape(batch_size, c.num_samples).amax(1)
            target_q = b.reward + c.gamma * b.discount * q_t
        s_c = n.critic_enc(obs)
        loss_c, m = critic_loss(*n.q(s_c, action), target_q)
        metrics.update(m)
        common.sgd_step(self.optimizers["critic"], loss_c)

        with torch.no_grad():
            sampled = n.vae.decode(s_vae.detach(), g)
        perturbed = n.perturb(n.actor_enc(obs), sampled, c.phi)
        loss_a = -n.q_first(n.critic_enc(obs), perturbed).mean()
        metrics["actor/loss"] = loss_a
        common.sgd_step(self.optimizers["actor"], loss_a, inputs=self.actor_params)

        self.step = common.advance(self.step, c.target_update_period, self.targets, c.tau)
        return common.metrics_to_floats(metrics)

    def next_value(self, next_obs: common.TensorObservation) -> torch.Tensor:
        """Soft clipped double-Q of ``num_samples`` perturbed VAE actions per next state, as
        (batch * num_samples,) rows; on a CPU in slices of ``cpu_slice_rows`` rows. The latents
        are drawn for all rows at once, so slicing leaves the random stream as it is."""
        c, n, t, reps = self.config, self.nets, self.target, self.config.num_samples
        sv = n.vae_enc(next_obs).repeat_interleave(reps, 0)  # the online VAE, as the original
        sa = t.actor_enc(next_obs).repeat_interleave(reps, 0)
        sc = t.critic_enc(next_obs).repeat_interleave(reps, 0)
        z = n.vae.prior_latent(sv.shape[0], self.generator, sv.device)
        rows = common.cpu_slices(self.device, c.cpu_slice_rows, len(sv))
        values = []
        for sv_i, sa_i, sc_i, z_i in zip(
            sv.split(rows), sa.split(rows), sc.split(rows), z.split(rows), strict=True
        ):
            next_a = t.perturb(sa_i, n.vae.decode(sv_i, z=z_i), c.phi)
            values.append(clipped_double_q(*t.q(sc_i, next_a), c.lmbda))
        return torch.cat(values)

    @torch.inference_mode()
    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """Scores ``num_samples`` perturbed VAE actions with Q1 and returns the best (the
        original's ``select_action``); latents from a generator seeded with 0 when greedy."""
        n, reps = self.nets, self.config.num_samples
        g = common.generator(0, self.device) if greedy else self.generator
        obs = common.to_torch(observation, self.device)
        sv = n.vae_enc(obs).repeat_interleave(reps, 0)
        sa = n.actor_enc(obs).repeat_interleave(reps, 0)
        sc = n.critic_enc(obs).repeat_interleave(reps, 0)
        a = n.perturb(sa, n.vae.decode(sv, g), self.config.phi)
        q1 = n.q_first(sc, a).reshape(-1, reps)
        best = q1.argmax(1) + torch.arange(q1.shape[0], device=q1.device) * reps
        return self.scaler.from_unit(a[best])

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = BCQAgent
