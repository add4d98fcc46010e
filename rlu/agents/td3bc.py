"""TD3+BC (Fujimoto and Gu 2021, "A Minimalist Approach to Offline Reinforcement Learning").

TD3 (Fujimoto et al. 2018) with two changes and nothing else: a behaviour-cloning term in the
actor's loss, and observations standardised with the whole dataset's statistics:

    s      <- (s - mean_D) / (std_D + 1e-3)                   (every feature, once per run)
    a'     =  clip(pi'(s') + clip(sigma eps, -c, c), -1, 1),    eps ~ N(0, I)
    L_Q    =  sum_i E[(Q_i(s, a) - r - gamma d min_j Q'_j(s', a'))^2]
    L_pi   =  -lambda E[Q_1(s, pi(s))] + E[(pi(s) - a)^2]
    lambda =  alpha / E|Q_1(s, pi(s))|

with lambda held fixed (no gradient) in each actor step. Original code: github.com/sfujim/TD3_BC
(``TD3_BC.py``: networks and update; ``main.py``: settings; ``utils.py``: ``normalize_states``);
CORL's ``algorithms/offline/td3_bc.py`` (github.com/tinkoff-ai/CORL) is the same algorithm.
The ``paper`` preset is the paper's table and the original's defaults: actor and critics 256-256
ReLU MLPs (the actor's output through tanh), Adam 3e-4 for both, batch 256, discount 0.99,
Polyak rate 0.005, target policy noise 0.2 clipped to 0.5, the actor and the targets updated on
every second update (policy_freq 2), alpha 2.5, 1M updates, observation normalisation on. As the
original: the critics learn on every update; on updates 2, 4, 6, ... (its ``total_it %
policy_freq == 0``) the actor then learns from the freshly updated first critic, and only then do
the target actor and target critics move. The observation statistics come through the loop's
dataset-statistics contract: ``batch_spec.statistics = ("observation",)``, the loop computes
them once (``rlu.data.statistics``) and calls :meth:`TD3BCAgent.set_statistics`; they live in
the agent's state (the ``normaliser`` module's buffers), so a checkpoint evaluates and resumes
with them, and ``act`` normalises what it is given as the original's evaluation does.

``GRID`` is empty: the paper runs every D4RL dataset with one alpha (2.5), which is its point; it
varies alpha only to show the sensitivity, not to pick a value per dataset. A sweep over alpha is
``rlu sweep --grid alpha=...`` like any field.

Deviations and choices:
- Statistics over every step of the dataset, each episode's final observation included; the
  original takes them over D4RL's ``qlearning_dataset`` observations, which leave the final
  one out (one observation per episode).
- Observations go through ``networks.Encoder``: float entries normalised per key, then joined in
  sorted-key order; camera images are not normalised (the data's statistics leave them out) and
  go through the ResNet torso. The twin critics share one encoder (``networks.TwinCritic``).
- Actions are learned in [-1, 1] (``networks.ActionScaler``); the original scales the target
  noise by ``max_action``, the same thing for the symmetric boxes of its tasks.
- ``actor/*`` metrics are reported on the updates that step the actor only; the loop's default
  logging period is even, so every logged step has them.
- ``update`` refuses to run before :meth:`set_statistics` (a run normalised with mean 0 and std 1
  would be another algorithm, silently); ``normalize_observations=False`` is the original's
  ``--normalize False``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch.nn import functional as F

from rlu.agents import common
from rlu.agents import networks as nets
from rlu.agents.losses import smoothed_target_action
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
from rlu.types import (
    ActionSpec,
    BatchSpec,
    DataStatistics,
    Observation,
    ObservationSpec,
    Transition,
)


@dataclass(frozen=True)
class TD3BCConfig(Checked):
    hidden_layers: tuple[int, ...] = field(default=(256, 256), metadata=LAYERS)
    """Hidden sizes of the actor and of each critic (ReLU MLPs)."""
    torso_hidden: int = field(default=64, metadata=WIDTH)
    """Camera ResNet embedding size."""
    alpha: float = field(default=2.5, metadata=bounds(min=0.0, max=1e6))
    """alpha of lambda = alpha / E|Q|: the weight of the Q term against behaviour cloning."""
    policy_noise: float = field(default=0.2, metadata=bounds(min=0.0, max=1e3))
    """Standard deviation of the target policy smoothing noise (actions in [-1, 1])."""
    noise_clip: float = field(default=0.5, metadata=bounds(min=0.0, max=1e3))
    """The smoothing noise is clipped to [-noise_clip, noise_clip]."""
    policy_freq: int = field(default=2, metadata=bounds(min=1, max=1000))
    """The actor and the target networks learn on every policy_freq-th update."""
    gamma: float = field(default=0.99, metadata=FRACTION)
    """Discount."""
    tau: float = field(default=0.005, metadata=bounds(gt=0.0, max=1.0))
    """Polyak rate of the target actor and critics, on the updates that step the actor."""
    actor_lr: float = field(default=3e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the actor."""
    critic_lr: float = field(default=3e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the twin critics."""
    normalize_observations: bool = True
    """Standardise observations with the dataset's per-feature mean and std."""
    observation_eps: float = field(default=1e-3, metadata=bounds(gt=0.0, max=1e3))
    """eps of (s - mean) / (std + eps), the original's ``normalize_states(eps=1e-3)``."""
    batch_size: int = field(default=256, metadata=BATCH)
    """Transitions per update."""
    num_steps: int = field(default=1_000_000, metadata=STEPS)
    """Learner steps of a full run (the original's ``max_timesteps`` 1M)."""


Config = TD3BCConfig
PRESETS = {
    "paper": TD3BCConfig(),
    "small": TD3BCConfig(num_steps=20_000),  # the paper's networks are already small
}
GRID: dict[str, list] = {}  # one alpha for every dataset is the paper's point (docstring)


def critic_target(
    reward: torch.Tensor, discount: torch.Tensor, bootstrap_gamma: float, next_q: torch.Tensor
) -> torch.Tensor:
    """r + gamma^n d min_j Q'_j(s', a') from the target critics' (2, B) values."""
    return reward + bootstrap_gamma * discount * next_q.amin(0)


def critic_loss(q: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, common.Metrics]:
    """Sum over the twin critics (2, B) of the mean squared error to the fixed target (B,)."""
    loss = (q - target.detach()).pow(2).mean(1).sum()
    return loss, {"critic/loss": loss, "critic/q_mean": q.mean()}


def actor_loss(
    q: torch.Tensor, policy_action: torch.Tensor, action: torch.Tensor, alpha: float
) -> tuple[torch.Tensor, common.Metrics]:
    """-lambda mean Q_1(s, pi(s)) + mean (pi(s) - a)^2 with lambda = alpha / mean |Q_1|, the
    scale held fixed; ``q`` (B,) is Q_1 at the policy's actions (B, A), ``action`` the data's."""
    lmbda = alpha / q.abs().mean().detach()
    bc = F.mse_loss(policy_action, action)
    loss = -lmbda * q.mean() + bc
    return loss, {"actor/loss": loss, "actor/bc_loss": bc, "actor/lambda": lmbda,
                  "actor/q_mean": q.mean()}  # fmt: skip


class TD3BCAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: TD3BCConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.scaler = nets.ActionScaler(action_spec)
        self.normaliser = nets.ObservationNormaliser(
            observation_spec, config.observation_eps, config.normalize_observations
        ).to(self.device)
        self.batch_spec = BatchSpec(
            config.batch_size, gamma=config.gamma, statistics=self.normaliser.statistics
        )
        self.num_steps, self.pretrain_steps = config.num_steps, 0
        a, d, layers, th = self.scaler.dim, self.device, config.hidden_layers, config.torso_hidden
        self.generator = common.generator(stream_seed(seed, "learner"), d)
        with common.seeded(seed):
            self.actor = nets.DeterministicPolicy(observation_spec, a, layers, th).to(d)
            self.critics = nets.TwinCritic(observation_spec, a, layers, th).to(d)
        built = common.actor_critic(
            self.actor, self.critics, config.actor_lr, config.critic_lr, ("actor", "critics"),
            {"normaliser": self.normaliser},
        )  # fmt: skip
        self.target_actor, self.target_critics = built.target_actor, built.target_critic
        self.actor_params = list(self.actor.parameters())
        self.modules, self.optimizers = built.modules, built.optimizers
        self.generators = {"noise": self.generator}

    def set_statistics(self, stats: DataStatistics) -> None:
        """Take the dataset's observation mean and std (the loop computes them once, before the
        first update); they are kept in the agent's state from then on."""
        self.normaliser.set(stats)

    def update(self, batch: Transition) -> dict[str, float]:
        self.normaliser.require("td3bc")
        c = self.config
        b = common.transition(batch, self.scaler, self.device)
        # every network here encodes the same spec: the keys are joined once per batch
        flat, norm = self.critics.encoder.flatten, self.normaliser
        obs, next_obs = flat(norm(b.observation)), flat(norm(b.next_observation))

        with torch.no_grad():
            next_action = smoothed_target_action(
                self.target_actor(next_obs), c.policy_noise, c.noise_clip, self.generator
            )
            next_q = self.target_critics(next_obs, next_action)
            target = critic_target(b.reward, b.discount, self.batch_spec.bootstrap_gamma, next_q)
        loss_q, metrics = critic_loss(self.critics(obs, b.action), target)
        common.sgd_step(self.optimizers["critic"], loss_q)

        actor_step = (self.step + 1) % c.policy_freq == 0  # the original's total_it, 1-based
        if actor_step:
            policy_action = self.actor(obs)
            q = self.critics.first(obs, policy_action)
            loss_a, m = actor_loss(q, policy_action, b.action, c.alpha)
            metrics.update(m)
            common.sgd_step(self.optimizers["actor"], loss_a, inputs=self.actor_params)
        targets = {self.target_critics: self.critics, self.target_actor: self.actor}
        self.step = common.advance(self.step, 0, targets, c.tau if actor_step else 0.0)
        return common.metrics_to_floats(metrics)

    @torch.inference_mode()
    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """pi(s) of the normalised observation, greedy or not: the policy is deterministic and,
        offline, acts without TD3's exploration noise."""
        obs = self.normaliser(common.to_torch(observation, self.device))
        return self.scaler.from_unit(self.actor(obs))

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = TD3BCAgent
