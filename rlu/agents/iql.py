"""Implicit Q-Learning, IQL (Kostrikov, Nair and Levine 2021, "Offline Reinforcement Learning
with Implicit Q-Learning").

IQL never queries the critic at an action outside the data. A state value V is fitted as an
upper expectile of the (target) twin critics' min Q over the data's actions, Q regresses onto
r + gamma d V(s'), and the policy is extracted by advantage-weighted regression (AWR):

    L_V  = E_(s,a)~D [ |tau - 1(u < 0)| u^2 ],  u = min_i Q'_i(s, a) - V(s)
    L_Q  = E_(s,a,r,s')~D [ sum_i (Q_i(s, a) - r - gamma d V(s'))^2 ]
    L_pi = -E_(s,a)~D [ min(exp(beta (min_i Q'_i(s, a) - V(s))), 100) log pi(a | s) ]

Original code: github.com/ikostrikov/implicit_q_learning (``learner.py``, ``critic.py``,
``actor.py``, ``policy.py``, ``configs/mujoco_config.py``). The ``paper`` preset is its MuJoCo
(D4RL locomotion) setting, the paper's appendix table: expectile tau = 0.7, inverse temperature
beta = 3.0, 2 x 256 ReLU MLPs for V, each Q and the policy, Adam 3e-4 for all three with a cosine
decay of the policy's rate to 0 over the run (``opt_decay_schedule="cosine"``), Polyak targets
tau = 0.005, discount 0.99, batch 256, 1M updates, no dropout. As the original, one update is
V, then the policy (with the new V), then Q (with the new V), then the target critics. The
policy is a Gaussian with mean tanh(MLP(s)) and a state-independent log std clipped to [-5, 2]
(not tanh-squashed); ``act(greedy=True)`` returns its mean (the original evaluates at
temperature 0), ``greedy=False`` samples it.

Deviations and choices:
- Reward normalisation: for locomotion the original rescales the dataset's rewards by
  1000 / (max - min episode return). An agent here sees batches, not datasets, so that is a
  data-side choice; ``reward_scale`` multiplies every reward if wanted. RL Unplugged's control
  suite needs none: per-step rewards lie in [0, 1] over 1000-step episodes, so returns already
  span at most 1000.
- Observations go through ``networks.Encoder`` (one per network; cameras through the ResNet
  torso); the twin critics (``networks.TwinCritic``) share one encoder.
- torch's default initialisation instead of the original's orthogonal one.
- The cosine horizon is ``num_steps`` (the original's ``max_steps``); a run stopped earlier
  ends before the policy's rate reaches 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents import networks as nets
from rlu.agents.losses import gaussian_log_prob
from rlu.files import (
    BATCH,
    FRACTION,
    LAYERS,
    LEARNING_RATE,
    STEPS,
    WIDTH,
    Checked,
    bounds,
)
from rlu.seeds import stream_seed
from rlu.types import ActionSpec, BatchSpec, Observation, ObservationSpec, Transition


@dataclass(frozen=True)
class IQLConfig(Checked):
    hidden_layers: tuple[int, ...] = field(default=(256, 256), metadata=LAYERS)
    """Hidden sizes of the value, each critic and the policy (ReLU MLPs)."""
    torso_hidden: int = field(default=64, metadata=WIDTH)
    """Camera ResNet embedding size."""
    expectile: float = field(default=0.7, metadata=bounds(gt=0.0, lt=1.0))
    """tau of the expectile value loss (MuJoCo 0.7; the paper's AntMaze 0.9)."""
    beta: float = field(default=3.0, metadata=bounds(min=0.0, max=1e6))
    """Inverse temperature of the AWR weights exp(beta A) (MuJoCo 3.0; AntMaze 10.0)."""
    max_weight: float = field(default=100.0, metadata=bounds(gt=0.0, max=1e12))
    """Cap on the AWR weights."""
    log_std_min: float = field(default=-5.0, metadata=bounds(min=-100.0, max=100.0))
    """Lower clip of the policy's log standard deviation."""
    log_std_max: float = field(default=2.0, metadata=bounds(min=-100.0, max=100.0))
    """Upper clip of the policy's log standard deviation."""
    gamma: float = field(default=0.99, metadata=FRACTION)
    """Discount."""
    tau: float = field(default=0.005, metadata=bounds(gt=0.0, max=1.0))
    """Polyak rate of the target critics, every update."""
    reward_scale: float = field(default=1.0, metadata=bounds(gt=0.0, max=1e6))
    """Factor on every reward before the target (see the module docstring)."""
    actor_lr: float = field(default=3e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the policy (its start value with the cosine schedule)."""
    critic_lr: float = field(default=3e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the twin critics."""
    value_lr: float = field(default=3e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the value network."""
    cosine_decay: bool = True
    """Decay the policy's learning rate to 0 along a half cosine over ``num_steps`` updates."""
    batch_size: int = field(default=256, metadata=BATCH)
    """Transitions per update."""
    num_steps: int = field(default=1_000_000, metadata=STEPS)
    """Learner steps of a full run (the original's 1M); also the cosine schedule's horizon."""


Config = IQLConfig
PRESETS = {
    "paper": IQLConfig(),
    "small": IQLConfig(num_steps=20_000),  # the paper's networks are already small
}
GRID: dict[str, list] = {}  # the paper fixes tau and beta per domain; no sweep


def expectile_loss(diff: torch.Tensor, expectile: float) -> torch.Tensor:
    """Asymmetric squared loss |tau - 1(u < 0)| u^2 of u = Q - V, averaged: (B,) -> ()."""
    weight = torch.where(diff > 0, expectile, 1.0 - expectile)
    return (weight * diff.pow(2)).mean()


def value_loss(
    q_min: torch.Tensor, v: torch.Tensor, expectile: float
) -> tuple[torch.Tensor, common.Metrics]:
    """L_V with the target critics' min Q(s, a) held fixed."""
    loss = expectile_loss(q_min.detach() - v, expectile)
    return loss, {"value/loss": loss, "value/v_mean": v.mean()}


def critic_loss(q: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, common.Metrics]:
    """Sum over the twin critics (2, B) of the mean squared error to the target (B,)."""
    loss = (q - target.detach()).pow(2).mean(1).sum()
    return loss, {"critic/loss": loss, "critic/q_mean": q.mean()}


def awr_weights(adv: torch.Tensor, beta: float, max_weight: float) -> torch.Tensor:
    """min(exp(beta A), max_weight)."""
    return torch.exp(beta * adv).clamp(max=max_weight)


def actor_loss(
    log_prob: torch.Tensor, adv: torch.Tensor, beta: float, max_weight: float
) -> tuple[torch.Tensor, common.Metrics]:
    """AWR: -mean_b w_b log pi(a_b | s_b), weights from the fixed advantage."""
    w = awr_weights(adv.detach(), beta, max_weight)
    loss = -(w * log_prob).mean()
    return loss, {"actor/loss": loss, "actor/weight_mean": w.mean(),
                  "actor/advantage_mean": adv.mean()}  # fmt: skip


def cosine_lr(base: float, step: int, horizon: int) -> float:
    """optax's ``cosine_decay_schedule(base, horizon)`` at update ``step`` (0-based)."""
    frac = min(step, horizon) / horizon
    return base * 0.5 * (1.0 + math.cos(math.pi * frac))


class ValueNet(nn.Module):
    def __init__(self, observation_spec: ObservationSpec, c: IQLConfig) -> None:
        super().__init__()
        self.encoder = nets.Encoder(observation_spec, c.torso_hidden)
        self.net = nets.mlp(self.encoder.output_dim, c.hidden_layers, 1)

    def forward(self, obs: common.TensorObservation) -> torch.Tensor:
        return self.net(self.encoder(obs)).squeeze(-1)


class GaussianPolicy(nn.Module):
    """N(tanh(MLP(s)), exp(log_std)) with a state-independent, clipped log std."""

    def __init__(self, observation_spec: ObservationSpec, action_dim: int, c: IQLConfig) -> None:
        super().__init__()
        self.encoder = nets.Encoder(observation_spec, c.torso_hidden)
        self.net = nets.mlp(self.encoder.output_dim, c.hidden_layers, action_dim)
        self.log_std = nn.Parameter(torch.zeros(action_dim))
        self.log_std_range = (c.log_std_min, c.log_std_max)

    def forward(self, obs: common.TensorObservation) -> tuple[torch.Tensor, torch.Tensor]:
        mean = torch.tanh(self.net(self.encoder(obs)))
        std = self.log_std.clamp(*self.log_std_range).exp().expand_as(mean)
        return mean, std


class IQLAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: IQLConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.scaler = nets.ActionScaler(action_spec)
        self.batch_spec = BatchSpec(config.batch_size, gamma=config.gamma)
        self.num_steps, self.pretrain_steps = config.num_steps, 0
        a, d, layers, th = self.scaler.dim, self.device, config.hidden_layers, config.torso_hidden
        self.generator = common.generator(stream_seed(seed, "learner"), d)
        with common.seeded(seed):
            self.value = ValueNet(observation_spec, config).to(d)
            self.critics = nets.TwinCritic(observation_spec, a, layers, th).to(d)
            self.policy = GaussianPolicy(observation_spec, a, config).to(d)
        self.target_critics = common.frozen_copy(self.critics)
        self.modules = {
            "value": self.value, "critics": self.critics, "policy": self.policy,
            "target_critics": self.target_critics,
        }  # fmt: skip
        self.optimizers = {
            "value": common.adam(self.value.parameters(), config.value_lr),
            "critic": common.adam(self.critics.parameters(), config.critic_lr),
            "policy": common.adam(self.policy.parameters(), config.actor_lr),
        }
        self.generators = {"sample": self.generator}

    def update(self, batch: Transition) -> dict[str, float]:
        c = self.config
        b = common.transition(batch, self.scaler, self.device)
        # every network here encodes the same spec: the keys are concatenated once per batch
        obs, next_obs = (
            self.value.encoder.flatten(b.observation),
            self.value.encoder.flatten(b.next_observation),
        )
        action, reward = b.action, b.reward * c.reward_scale

        with torch.no_grad():
            q_min = self.target_critics(obs, action).amin(0)
        loss_v, metrics = value_loss(q_min, self.value(obs), c.expectile)
        common.sgd_step(self.optimizers["value"], loss_v)

        with torch.no_grad():  # the policy and the critics both see the updated V
            v, v_next = self.value(nets.cat_batches(obs, next_obs)).split(len(reward))  # one pass
            adv = q_min - v
            target = reward + self.batch_spec.bootstrap_gamma * b.discount * v_next
        if c.cosine_decay:
            lr = cosine_lr(c.actor_lr, self.step, c.num_steps)
            for group in self.optimizers["policy"].param_groups:
                group["lr"] = lr
        mean, std = self.policy(obs)
        loss_a, m = actor_loss(gaussian_log_prob(mean, std, action), adv, c.beta, c.max_weight)
        metrics.update(m)
        common.sgd_step(self.optimizers["policy"], loss_a)

        loss_q, m = critic_loss(self.critics(obs, action), target)
        metrics.update(m)
        common.sgd_step(self.optimizers["critic"], loss_q)
        self.step = common.advance(self.step, 0, {self.target_critics: self.critics}, c.tau)
        return common.metrics_to_floats(metrics)

    @torch.inference_mode()
    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """The Gaussian's mean (the original evaluates at temperature 0) with ``greedy=True``;
        with ``greedy=False`` a sample of N(mean, exp(log_std)) from the agent's generator."""
        mean, std = self.policy(common.to_torch(observation, self.device))
        if not greedy:
            noise = torch.randn(mean.shape, generator=self.generator, device=mean.device)
            mean = mean + std * noise
        return self.scaler.from_unit(mean)

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = IQLAgent
