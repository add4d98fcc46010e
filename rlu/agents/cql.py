"""Conservative Q-Learning for continuous actions, CQL(H) (Kumar, Zhou, Tucker and Levine 2020,
"Conservative Q-Learning for Offline Reinforcement Learning").

SAC with twin critics, plus a regulariser that pushes Q down on actions the policy or a uniform
proposal would pick and up on the data's actions. Per critic i, with N actions from each of
three proposals (uniform on [-1, 1]^A, pi(.|s), pi(.|s')) importance-weighted by their density:

    R_i = T E_s[ log sum_j exp((Q_i(s, a_j) - log mu(a_j)) / T) ] - E_(s,a)~D[ Q_i(s, a) ]
    L_Q_i = E[(Q_i(s, a) - r - gamma d min_k Q'_k(s', a'))^2] + alpha' R_i,  a' ~ pi(s')

(CQL(H) with the importance-sampled log-sum-exp, ``min_q_version=3`` in the original).
alpha' is fixed (``cql_weight``) or, with ``lagrange_threshold`` set, a Lagrange multiplier
trained to hold R_i near the threshold: alpha' (R_i - threshold) in the critic loss and
-alpha' (R_1 + R_2 - 2 threshold) / 2 on alpha'. The policy is SAC's: minimise
E[alpha log pi(a|s) - min_i Q_i(s, a)], a ~ pi(s), with the entropy weight alpha tuned
automatically towards the target entropy -|A|; for the first ``bc_steps`` updates it clones
the data instead, E[alpha log pi(a|s) - log pi(a_data|s)] (the original's ``policy_eval_start``).

Original code: github.com/aviralkumar2907/CQL, ``d4rl/rlkit/torch/sac/cql.py`` and
``d4rl/examples/cql_mujoco_new.py``; the ``paper`` preset is its README's command for the Gym
MuJoCo tasks: ``--policy_lr=1e-4 --lagrange_thresh=-1.0 --min_q_weight=5.0 --min_q_version=3``
(fixed alpha' = 5; the README names min_q_weight 5 or 10 and policy_lr 1e-4 or 3e-4, the
``GRID``), with the script's other settings: 3 x 256 ReLU MLPs for the tanh-Gaussian policy
and each critic, critic Adam 3e-4, the entropy weight's Adam at the policy's rate, Polyak
targets tau = 0.005, discount 0.99, batch 256, N = 10 actions per proposal, T = 1,
``policy_eval_start`` 40 000, ``deterministic_backup`` (no entropy term in the target), no max
backup. As the original, every proposal and target action of an update is drawn before the
policy's step, then alpha, the policy and the critics step; the pi(.|s') proposals are scored
at s (the original's ``q1_next_actions`` evaluates Q(s, a'), a' ~ pi(s'), kept as is).

Deviations and choices:
- Observations go through ``networks.Encoder`` (cameras through the ResNet torso); the twin
  critics (``networks.TwinCritic``) share one encoder, the tanh-Gaussian policy
  (``networks.TanhGaussianPolicy``, log std clipped to rlkit's [-20, 2]) has its own.
- The data's actions are clipped to +-(1 - 1e-4) before the policy's log density in the cloning
  phase (atanh of exactly +-1 is infinite; rlkit adds 1e-6 inside its logarithm instead).
- ``reward_scale`` (the original's, 1 for MuJoCo) multiplies every reward; RL Unplugged's control
  suite needs no rescaling (rewards in [0, 1]).
- ``act(greedy=True)`` returns tanh(mean), the original's deterministic evaluation policy;
  ``greedy=False`` samples the tanh-Gaussian.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents import networks as nets
from rlu.agents.losses import tanh_gaussian_log_prob
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

LOG_STD_RANGE = (-20.0, 2.0)  # rlkit's TanhGaussianPolicy
CLIP = 1.0 - 1e-4


@dataclass(frozen=True)
class CQLConfig(Checked):
    policy_layers: tuple[int, ...] = field(
        default=(256, 256, 256),
        metadata=LAYERS,
    )
    """Hidden sizes of the tanh-Gaussian policy (ReLU)."""
    critic_layers: tuple[int, ...] = field(
        default=(256, 256, 256),
        metadata=LAYERS,
    )
    """Hidden sizes of each of the twin critics (ReLU)."""
    torso_hidden: int = field(default=64, metadata=WIDTH)
    """Camera ResNet embedding size."""
    cql_weight: float = field(default=5.0, metadata=bounds(min=0.0, max=1e6))
    """alpha': weight of the conservative regulariser (fixed, or the multiplier's start)."""
    lagrange_threshold: float | None = field(default=None, metadata=bounds(min=0.0, max=1e6))
    """With a value, alpha' is a Lagrange multiplier holding the regulariser near it (the
    original's ``lagrange_thresh``: 10 for AntMaze); None keeps alpha' fixed (Gym MuJoCo)."""
    cql_temperature: float = field(default=1.0, metadata=bounds(gt=0.0, max=1e6))
    """T of the log-sum-exp."""
    num_samples: int = field(default=10, metadata=bounds(min=1, max=10_000))
    """N: actions per proposal (uniform, pi(s), pi(s')) in the log-sum-exp."""
    target_entropy: float | None = field(default=None, metadata=bounds(min=-1e6, max=1e6))
    """Target of the entropy tuning; None means -(action dimensions), SAC's default."""
    bc_steps: int = field(default=40_000, metadata=bounds(min=0, max=MAX_STEPS))
    """Updates during which the policy clones the data instead of maximising Q."""
    gamma: float = field(default=0.99, metadata=FRACTION)
    """Discount."""
    tau: float = field(default=0.005, metadata=bounds(gt=0.0, max=1.0))
    """Polyak rate of the target critics, every update."""
    reward_scale: float = field(default=1.0, metadata=bounds(gt=0.0, max=1e6))
    """Factor on every reward before the target."""
    policy_lr: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the policy."""
    critic_lr: float = field(default=3e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the critics and of the Lagrange multiplier."""
    alpha_lr: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the entropy weight (the original uses the policy's rate)."""
    batch_size: int = field(default=256, metadata=BATCH)
    """Transitions per update."""
    num_steps: int = field(default=1_000_000, metadata=STEPS)
    """Learner steps of a full run: what ``rlu train`` runs when no --steps is given. rlu's
    choice, as for the other continuous baselines (the README reports numbers at 500k)."""


Config = CQLConfig
PRESETS = {
    "paper": CQLConfig(),
    # Minutes on a CPU: each update scores 3N + 1 actions per state with both critics, so N = 4
    # (bench/README.md, design choices); cloning for the first 5 %.
    "small": CQLConfig(policy_layers=(256, 256), critic_layers=(256, 256), num_samples=4,
                       bc_steps=1_000, policy_lr=3e-4, alpha_lr=3e-4, num_steps=20_000),
}  # fmt: skip
GRID: dict[str, list] = {"cql_weight": [5.0, 10.0], "policy_lr": [1e-4, 3e-4]}


def cql_regulariser(q_rand: torch.Tensor, q_curr: torch.Tensor, q_next: torch.Tensor,
                    log_pi_curr: torch.Tensor, log_pi_next: torch.Tensor, q_data: torch.Tensor,
                    action_dim: int, temperature: float) -> torch.Tensor:  # fmt: skip
    """CQL(H)'s importance-sampled regulariser R_i of each critic, before its weight.

    q_rand, q_curr, q_next (C, N, B): C critics at N uniform, pi(s) and pi(s') proposals;
    log_pi_curr, log_pi_next (N, B) their log densities; q_data (C, B) at the data's actions.
    A uniform proposal on [-1, 1]^A has log density A log(1/2). Returns (C,).
    """
    log_uniform = action_dim * math.log(0.5)
    logits = torch.cat([q_rand - log_uniform, q_next - log_pi_next.detach(),
                        q_curr - log_pi_curr.detach()], dim=1)  # fmt: skip
    lse = temperature * torch.logsumexp(logits / temperature, dim=1).mean(-1)
    return lse - q_data.mean(-1)


def critic_loss(
    q_data: torch.Tensor,
    target: torch.Tensor,
    regulariser: torch.Tensor,
    cql_weight: float,
    alpha_prime: torch.Tensor | None = None,
    threshold: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None, common.Metrics]:
    """Twin critics' TD error plus the weighted regulariser; with a ``threshold``, the
    Lagrangian alpha' (w R_i - threshold) and alpha''s own loss -mean_i alpha' (w R_i - thr).

    q_data (C, B), target (B,), regulariser (C,). Returns (critic loss, alpha' loss or None,
    metrics).
    """
    td = (q_data - target.detach()).pow(2).mean(1)
    penalty = cql_weight * regulariser
    prime_loss = None
    if threshold is not None:
        if alpha_prime is None:  # the Lagrangian's multiplier comes with its threshold
            raise RluError("cql critic_loss: a threshold needs alpha_prime (a bug in rlu)")
        prime_loss = -(alpha_prime * (penalty.detach() - threshold)).mean()
        penalty = alpha_prime.detach() * (penalty - threshold)
    loss = (td + penalty).sum()
    metrics = {
        "critic/loss": loss,
        "critic/td_loss": td.sum(),
        "critic/regulariser": regulariser.mean(),
        "critic/q_mean": q_data.mean(),
    }
    if alpha_prime is not None:
        metrics["critic/alpha_prime"] = alpha_prime.detach()
    return loss, prime_loss, metrics


def alpha_loss(
    log_alpha: torch.Tensor, log_pi: torch.Tensor, target_entropy: float
) -> tuple[torch.Tensor, common.Metrics]:
    """SAC's entropy tuning: -log_alpha (log pi + target entropy), log pi held fixed."""
    loss = -(log_alpha * (log_pi.detach() + target_entropy)).mean()
    return loss, {"alpha/loss": loss, "alpha/value": log_alpha.detach().exp()}


def policy_loss(
    alpha: torch.Tensor, log_pi: torch.Tensor, q_pi: torch.Tensor
) -> tuple[torch.Tensor, common.Metrics]:
    """SAC's policy loss alpha log pi(a|s) - min_i Q_i(s, a), a ~ pi(s) reparameterised."""
    loss = (alpha * log_pi - q_pi).mean()
    return loss, {"actor/loss": loss, "actor/entropy": -log_pi.mean()}


def bc_policy_loss(
    alpha: torch.Tensor, log_pi: torch.Tensor, log_prob_data: torch.Tensor
) -> tuple[torch.Tensor, common.Metrics]:
    """The cloning phase: alpha log pi(a|s) - log pi(a_data|s)."""
    loss = (alpha * log_pi - log_prob_data).mean()
    return loss, {"actor/loss": loss, "actor/entropy": -log_pi.mean()}


class CQLAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: CQLConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.scaler = nets.ActionScaler(action_spec)
        self.batch_spec = BatchSpec(config.batch_size, gamma=config.gamma)
        self.num_steps, self.pretrain_steps = config.num_steps, 0
        self.generator = common.generator(stream_seed(seed, "learner"), self.device)
        a, d, th = self.scaler.dim, self.device, config.torso_hidden
        self.target_entropy = -float(a) if config.target_entropy is None else config.target_entropy
        with common.seeded(seed):
            self.policy = nets.TanhGaussianPolicy(
                observation_spec, a, config.policy_layers, th, LOG_STD_RANGE
            ).to(d)
            self.critics = nets.TwinCritic(observation_spec, a, config.critic_layers, th).to(d)
        self.target_critics = common.frozen_copy(self.critics)
        duals = {"log_alpha": nn.Parameter(torch.zeros(()))}
        if config.lagrange_threshold is not None:
            duals["log_alpha_prime"] = nn.Parameter(torch.zeros(()))
        self.duals = nn.ParameterDict(duals).to(d)
        self.optimizers = {
            "policy": common.adam(self.policy.parameters(), config.policy_lr),
            "critic": common.adam(self.critics.parameters(), config.critic_lr),
            "alpha": common.adam([self.duals["log_alpha"]], config.alpha_lr),
        }
        if config.lagrange_threshold is not None:
            self.optimizers["alpha_prime"] = common.adam(
                [self.duals["log_alpha_prime"]], config.critic_lr
            )
        self.modules = {
            "policy": self.policy, "critics": self.critics, "target_critics": self.target_critics,
            "duals": self.duals,
        }  # fmt: skip
        self.generators = {"sample": self.generator}

    def update(self, batch: Transition) -> dict[str, float]:
        c, g, n, d = self.config, self.generator, self.config.num_samples, self.device
        b = common.transition(batch, self.scaler, d)
        # the policy and the critics encode the same spec: the keys are concatenated once
        flatten = self.policy.encoder.flatten
        obs, next_obs = flatten(b.observation), flatten(b.next_observation)
        action, reward = b.action, b.reward * c.reward_scale

        # Every action the critics' side needs, drawn from the policy before its step.
        mean, std = self.policy(obs)
        with torch.no_grad():
            next_mean, next_std = self.policy(next_obs)
            next_a, _ = nets.sample_tanh_gaussian(next_mean, next_std, 1, g)
            q_next_target = self.target_critics(next_obs, next_a[0]).amin(0)
            target = reward + self.batch_spec.bootstrap_gamma * b.discount * q_next_target
            rand_a = torch.rand((n, *action.shape), generator=g, device=d) * 2.0 - 1.0
            curr_a, log_pi_curr = nets.sample_tanh_gaussian(mean, std, n, g)
            next_prop_a, log_pi_next = nets.sample_tanh_gaussian(next_mean, next_std, n, g)

        # Entropy weight, then the policy (SAC), cloning the data for the first bc_steps.
        pi_a, log_pi = nets.sample_tanh_gaussian(mean, std, 1, g)
        loss_alpha, metrics = alpha_loss(self.duals["log_alpha"], log_pi[0], self.target_entropy)
        common.sgd_step(self.optimizers["alpha"], loss_alpha)
        alpha = self.duals["log_alpha"].detach().exp()
        if self.step < c.bc_steps:
            u_data = torch.atanh(action.clamp(-CLIP, CLIP))
            log_prob_data = tanh_gaussian_log_prob(mean, std, u_data)
            loss_pi, m = bc_policy_loss(alpha, log_pi[0], log_prob_data)
        else:
            loss_pi, m = policy_loss(alpha, log_pi[0], self.critics(obs, pi_a[0]).amin(0))
        metrics.update(m)
        common.sgd_step(self.optimizers["policy"], loss_pi, inputs=list(self.policy.parameters()))

        # Critics: TD error plus the conservative regulariser (alpha' Lagrangian if asked).
        # one critic pass per proposal group, as the original: faster on the CPU than one
        # (3N + 1) x B pass (bench/README.md, design choices)
        q_data = self.critics(obs, action)
        q_rand, q_curr, q_next = (self.critics(obs, a) for a in (rand_a, curr_a, next_prop_a))
        reg = cql_regulariser(q_rand, q_curr, q_next, log_pi_curr, log_pi_next, q_data,
                              self.scaler.dim, c.cql_temperature)  # fmt: skip
        alpha_prime = None
        if c.lagrange_threshold is not None:
            alpha_prime = self.duals["log_alpha_prime"].exp().clamp(0.0, 1e6)
        loss_q, loss_prime, m = critic_loss(q_data, target, reg, c.cql_weight,
                                            alpha_prime, c.lagrange_threshold)  # fmt: skip
        metrics.update(m)
        if loss_prime is not None:
            common.sgd_step(self.optimizers["alpha_prime"], loss_prime)
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
        """tanh(mean), the original's deterministic evaluation policy, with ``greedy=True``;
        with ``greedy=False`` a sample of the tanh-Gaussian from the agent's generator."""
        mean, std = self.policy(common.to_torch(observation, self.device))
        if greedy:
            return self.scaler.from_unit(torch.tanh(mean))
        return self.scaler.from_unit(nets.sample_tanh_gaussian(mean, std, 1, self.generator)[0][0])

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = CQLAgent
