"""Critic Regularized Regression, CRR (Wang et al. 2020, "Critic Regularized Regression").

CRR was evaluated on these very datasets (the RL Unplugged control suite). The policy is fitted
by weighted regression onto the data's actions, the weights filtering actions by their advantage
under a learned critic:

    L_pi = -E_(s,a)~D [ f(A(s, a)) log pi(a | s) ],  A(s, a) = Q(s, a) - reduce_j Q(s, a_j),
    a_j ~ pi(s), j = 1..m;  f = min(exp(A / beta), ratio_upper_bound) ("exp") or 1[A > 0]
    ("binary"); reduce = mean or max over the m samples.

The critic is distributional (C51-style categorical, cross-entropy to the projected target
r + gamma d Z'(s', a'), a' ~ pi_target(s')). The paper reports two variants on these datasets,
CRR exp (mean baseline) and CRR binary (max baseline): presets ``paper`` and ``paper_binary``.

Original code: Acme's CRR learner (``acme/agents/tf/crr``, the feed-forward learner and the
recurrent ``RCRRLearner`` that the RL Unplugged notebook ``rl_unplugged/dm_control_suite_crr.ipynb``
runs on the control suite). From there: Adam 1e-4 for policy and critic, gradients clipped to a
global norm of 40, m = 4 samples, beta = 1, weights capped at 20, one target-policy action per
next state, targets copied every 100 updates, discount 0.99, batch 256 (the notebook); networks as
in the notebook: a residual MLP of 4 blocks x 1024 (8 layers) for policy and critic, a
5-component Gaussian-mixture policy head, a 21-atom categorical critic on [0, 100] (rewards in
[0, 1], discount 0.99: returns lie in [0, 100]).

Deviations:
- Feed-forward: the notebook's networks add two LSTM-1024 layers and learn from sequences; here
  the residual MLP feeds the heads directly and the agent learns from transitions (Acme's
  feed-forward learner), as rlu's other feed-forward continuous baselines.
- Observations go through ``networks.Encoder`` (features concatenated in sorted-key order,
  cameras through the ResNet torso) instead of the notebook's 300/400-unit ReLU encoders; the
  critic concatenates the action to the encoded observation before its MLP (Acme's
  ``CriticMultiplexer``), so the m sampled actions share one encoder pass.
- Mixture samples are clipped to [-1, 1] (the action box, in which the data lies) before the
  critic scores them; the mixture itself is unbounded, as in Acme.
- ``act(greedy=True)`` returns the mean of the most probable component (deterministic);
  ``greedy=False`` samples the mixture.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents import networks as nets
from rlu.agents.losses import (
    bootstrap_values,
    categorical_cross_entropy,
    categorical_projection,
    mixture_log_prob,
)
from rlu.files import (
    BATCH,
    FRACTION,
    LEARNING_RATE,
    MAX_LAYERS,
    STEPS,
    WIDTH,
    Checked,
    bounds,
)
from rlu.seeds import stream_seed
from rlu.types import ActionSpec, BatchSpec, Observation, ObservationSpec, RluError, Transition

WEIGHTS = ("exp", "binary")
BASELINES = ("mean", "max")


@dataclass(frozen=True)
class CRRConfig(Checked):
    hidden_size: int = field(default=1024, metadata=WIDTH)
    """Width of the residual MLPs of policy and critic."""
    num_layers: int = field(default=8, metadata=bounds(min=1, max=MAX_LAYERS))
    """Layers of each residual MLP (normalised every two)."""
    torso_hidden: int = field(default=64, metadata=WIDTH)
    """Camera ResNet embedding size (as the paper's ABM and BC)."""
    mixture_components: int = field(default=5, metadata=bounds(min=1, max=1024))
    """Gaussian components of the policy head."""
    num_atoms: int = field(default=21, metadata=bounds(min=2, max=10_000))
    """Atoms of the categorical critic."""
    vmin: float = field(default=0.0, metadata=bounds(min=-1e9, max=1e9))
    """Lowest atom."""
    vmax: float = field(default=100.0, metadata=bounds(min=-1e9, max=1e9))
    """Highest atom."""
    advantage_weight: str = field(default="exp", metadata=bounds(choices=WEIGHTS))
    """f(A): 'exp' (min(exp(A / beta), ratio_upper_bound)) or 'binary' (1[A > 0])."""
    baseline: str = field(default="mean", metadata=bounds(choices=BASELINES))
    """How the m critic values of policy samples reduce to V(s): 'mean' or 'max'."""
    num_advantage_samples: int = field(default=4, metadata=bounds(min=1, max=10_000))
    """m: policy samples per state in the advantage baseline."""
    beta: float = field(default=1.0, metadata=bounds(gt=0.0, max=1e6))
    """Temperature of the 'exp' weights."""
    ratio_upper_bound: float = field(default=20.0, metadata=bounds(gt=0.0, max=1e9))
    """Cap on the 'exp' weights."""
    num_target_samples: int = field(default=1, metadata=bounds(min=1, max=10_000))
    """Target-policy actions per next state; their distributions are averaged in the target."""
    gamma: float = field(default=0.99, metadata=FRACTION)
    """Discount."""
    target_update_period: int = field(default=100, metadata=STEPS)
    """Learner steps between hard copies into the target policy and critic."""
    policy_lr: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the policy."""
    critic_lr: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the critic."""
    max_grad_norm: float = field(default=40.0, metadata=bounds(min=0.0, max=1e9))
    """Global-norm clip of each network's gradient (Acme's ``clipping``); 0 switches it off."""
    batch_size: int = field(default=256, metadata=BATCH)
    """Transitions per update."""
    num_steps: int = field(default=1_000_000, metadata=STEPS)
    """Learner steps of a full run: what ``rlu train`` runs when no --steps is given. rlu's
    choice, as for the other continuous baselines."""


Config = CRRConfig
PRESETS = {
    "paper": CRRConfig(),
    "paper_binary": CRRConfig(advantage_weight="binary", baseline="max"),
    "small": CRRConfig(hidden_size=256, num_layers=2, policy_lr=3e-4, critic_lr=3e-4,
                       target_update_period=50, num_steps=20_000),
}  # fmt: skip
GRID: dict[str, list] = {}  # the paper compares named variants (the presets), not a grid


Mixture = tuple[torch.Tensor, torch.Tensor, torch.Tensor]
"""A ``MixtureHead``'s (logits, mean, std)."""


class Policy(nn.Module):
    """Encoder -> residual MLP -> Gaussian mixture over the unit-scaled action."""

    def __init__(self, observation_spec: ObservationSpec, action_dim: int, c: CRRConfig) -> None:
        super().__init__()
        self.torso = nets.Torso(
            observation_spec, c.hidden_size, c.num_layers, torso_hidden=c.torso_hidden
        )
        self.head = nets.MixtureHead(self.torso.output_dim, action_dim, c.mixture_components)

    def forward(self, obs: common.TensorObservation) -> Mixture:
        return self.head(self.torso(obs)[0])


def sample_actions(mixture: Mixture, num: int, generator: torch.Generator) -> torch.Tensor:
    """(num, B, A) actions from the (B,) mixtures, clipped into the action box."""
    logits, mean, std = (x.expand(num, *x.shape) for x in mixture)
    return nets.mixture_sample(logits, mean, std, generator=generator).clamp(-1.0, 1.0)


class Critic(nn.Module):
    """[Encoder(s), a] -> residual MLP -> logits over returns."""

    def __init__(self, observation_spec: ObservationSpec, action_dim: int, c: CRRConfig) -> None:
        super().__init__()
        self.encoder = nets.Encoder(observation_spec, c.torso_hidden)
        self.mlp = nets.ResidualMLP(self.encoder.output_dim + action_dim, c.hidden_size,
                                    c.num_layers)  # fmt: skip
        self.head = nets.CategoricalHead(c.hidden_size, c.num_atoms, c.vmin, c.vmax)

    def forward(self, obs: common.TensorObservation, action: torch.Tensor) -> torch.Tensor:
        """Logits for (B, A) actions, or (N, B, A): N actions per state, one encoder pass."""
        s = self.encoder(obs)
        s = s.expand(*action.shape[:-1], s.shape[-1])
        return self.head(self.mlp(torch.cat([s, action], -1)))


def advantage(q: torch.Tensor, q_samples: torch.Tensor, baseline: str) -> torch.Tensor:
    """A = Q(s, a) - reduce_j Q(s, a_j): q (B,), q_samples (m, B) of policy samples a_j."""
    v = q_samples.mean(0) if baseline == "mean" else q_samples.amax(0)
    return q - v


def crr_weights(
    adv: torch.Tensor, kind: str, beta: float, ratio_upper_bound: float
) -> torch.Tensor:
    """f(A): min(exp(A / beta), ratio_upper_bound) for 'exp', 1[A > 0] for 'binary'."""
    if kind == "exp":
        return torch.exp(adv / beta).clamp(max=ratio_upper_bound)
    return (adv > 0).to(adv.dtype)


def critic_loss(
    logits: torch.Tensor,
    target_probs: torch.Tensor,
    reward: torch.Tensor,
    discount: torch.Tensor,
    atoms: torch.Tensor,
    bootstrap_gamma: float,
) -> tuple[torch.Tensor, common.Metrics]:
    """Cross-entropy to the target distribution (``target_probs`` at s', over ``atoms``)
    shifted by r + gamma^n d and projected back onto the atoms."""
    values = bootstrap_values(reward, discount, bootstrap_gamma, atoms.expand(reward.shape[0], -1))
    target = categorical_projection(values, target_probs, atoms).detach()
    loss = categorical_cross_entropy(logits, target).mean()
    q = (torch.softmax(logits, -1) * atoms).sum(-1)
    return loss, {"critic/loss": loss, "critic/q_mean": q.mean()}


def policy_loss(
    log_prob: torch.Tensor, weights: torch.Tensor, adv: torch.Tensor
) -> tuple[torch.Tensor, common.Metrics]:
    """Critic-weighted regression: -mean_b f(A_b) log pi(a_b | s_b), weights held fixed."""
    w = weights.detach()
    loss = -(w * log_prob).mean()
    return loss, {"actor/loss": loss, "actor/weight_mean": w.mean(),
                  "actor/advantage_mean": adv.mean()}  # fmt: skip


class CRRAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: CRRConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        if config.advantage_weight not in WEIGHTS:
            raise RluError(f"CRRConfig.advantage_weight={config.advantage_weight!r}; "
                           f"use one of {', '.join(WEIGHTS)}")  # fmt: skip
        if config.baseline not in BASELINES:
            raise RluError(f"CRRConfig.baseline={config.baseline!r}; "
                           f"use one of {', '.join(BASELINES)}")  # fmt: skip
        self.config, self.device, self.step = config, common.device(device), 0
        self.scaler = nets.ActionScaler(action_spec)
        self.batch_spec = BatchSpec(config.batch_size, gamma=config.gamma)
        self.num_steps, self.pretrain_steps = config.num_steps, 0
        self.generator = common.generator(stream_seed(seed, "learner"), self.device)
        a, d = self.scaler.dim, self.device
        with common.seeded(seed):
            self.policy = Policy(observation_spec, a, config).to(d)
            self.critic = Critic(observation_spec, a, config).to(d)
        built = common.actor_critic(self.policy, self.critic, config.policy_lr, config.critic_lr)
        self.target_policy, self.target_critic = built.target_actor, built.target_critic
        self.modules, self.optimizers = built.modules, built.optimizers
        self.generators = {"sample": self.generator}
        # copied into their targets every target_update_period updates
        self.targets = built.targets

    def update(self, batch: Transition) -> dict[str, float]:
        c, g = self.config, self.generator
        b, atoms = common.transition(batch, self.scaler, self.device), self.critic.head.atoms
        obs, action = b.observation, b.action

        with torch.no_grad():
            next_a = sample_actions(self.target_policy(b.next_observation), c.num_target_samples, g)
            target_probs = torch.softmax(self.target_critic(b.next_observation, next_a), -1).mean(0)
        logits = self.critic(obs, action)
        loss_c, metrics = critic_loss(
            logits, target_probs, b.reward, b.discount, atoms, self.batch_spec.bootstrap_gamma
        )

        mix = self.policy(obs)
        with torch.no_grad():
            sampled = sample_actions(mix, c.num_advantage_samples, g)
            q_samples = self.critic.head.mean(self.critic(obs, sampled))
            adv = advantage(self.critic.head.mean(logits), q_samples, c.baseline)
            weights = crr_weights(adv, c.advantage_weight, c.beta, c.ratio_upper_bound)
        logits_p, mean, std = mix
        loss_p, m = policy_loss(mixture_log_prob(logits_p, mean, std, action), weights, adv)
        metrics.update(m)

        common.sgd_step(self.optimizers["critic"], loss_c, list(self.critic.parameters()),
                        c.max_grad_norm)  # fmt: skip
        common.sgd_step(self.optimizers["policy"], loss_p, list(self.policy.parameters()),
                        c.max_grad_norm)  # fmt: skip
        self.step = common.advance(self.step, c.target_update_period, self.targets)
        return common.metrics_to_floats(metrics)

    @torch.inference_mode()
    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """The mean of the mixture's most probable component with ``greedy=True``; with
        ``greedy=False`` a sample of the Gaussian mixture from the agent's generator."""
        logits, mean, std = self.policy(common.to_torch(observation, self.device))
        if greedy:
            return self.scaler.from_unit(nets.mixture_mode(logits, mean))
        return self.scaler.from_unit(nets.mixture_sample(logits, mean, std, self.generator))

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = CRRAgent
