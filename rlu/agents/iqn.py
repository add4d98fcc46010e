"""Implicit Quantile Networks, IQN (paper appendix A.2; Dabney et al. 2018).

Original code: Dopamine's ``ImplicitQuantileAgent`` and Acme's IQN learner. Z(s, tau) =
f(psi(s) * phi(tau)) with psi the Nature CNN, phi(tau) = ReLU(W cos(pi i tau) + b), i = 0..63,
and f the 512-unit head; the loss is the quantile Huber loss (kappa 1) between N online and
N' target quantiles, N = N' = ``num_tau_samples`` (the paper's 16, chosen from {8, 16, 32}).
The next action is the argmax of the mean target quantiles on the same N' fractions (Acme);
the paper names double-Q for DQN only (``double_q`` switches it on here too).
Deviations: Adam epsilon 1e-7 (TF2 default, as the paper states) instead of Dopamine's 0.01/32;
cos(pi i tau) starts at i = 0 as in the IQN paper (Dopamine: i = 1); the learning-rate grid is
{3e-5, 5e-5, 1e-4} (see ``discrete_common.LEARNING_RATE_GRID``).

Acting: ``greedy=True`` draws ``num_quantile_samples`` (K = 32) fractions per observation from
the agent's acting generator, takes argmax_a of the mean quantile, and replaces it by a uniform
action with probability ``atari.eval_epsilon`` (0.4^8); ``greedy=False`` uses
``atari.explore_epsilon`` (0.01).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from rlu.agents import common
from rlu.agents import discrete_common as dc
from rlu.files import LEARNING_RATE, WIDTH, Checked, bounds
from rlu.types import ActionSpec, Observation, ObservationSpec, Transition


@dataclass(frozen=True)
class IQNConfig(Checked):
    atari: dc.AtariSettings = field(default_factory=dc.AtariSettings)
    """Settings shared by the Atari baselines (batch, discount, network, epsilons, budget)."""
    learning_rate: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam step size; the paper's online policy selection picked 1e-4 for IQN."""
    num_tau_samples: int = field(default=16, metadata=bounds(min=1, max=10_000))
    """Quantile fractions drawn per transition, for the online (N) and the target (N') side."""
    num_quantile_samples: int = field(default=32, metadata=bounds(min=1, max=10_000))
    """Fractions drawn per observation to estimate Q when acting (Dopamine's K)."""
    embedding_size: int = field(default=64, metadata=WIDTH)
    """Cosine features of tau (n in the IQN paper)."""
    kappa: float = field(default=1.0, metadata=bounds(gt=0.0, max=1e6))
    """Where the quantile Huber loss turns linear."""
    double_q: bool = False
    """Select the next action with the online network instead of the target network."""


Config = IQNConfig

PRESETS: dict[str, IQNConfig] = {
    "paper": IQNConfig(),
    "small": IQNConfig(
        **dc.SMALL_FIELDS,
        num_tau_samples=8,
        num_quantile_samples=8,
        embedding_size=32,
    ),  # fmt: skip
}

GRID: dict[str, list[Any]] = {
    "learning_rate": list(dc.LEARNING_RATE_GRID),
    "num_tau_samples": [8, 16, 32],
}


def cosine_tau_embedding(taus: torch.Tensor, embedding_size: int) -> torch.Tensor:
    """IQN eq. (4): cos(pi i tau) for i = 0 .. n-1; (..., N) -> (..., N, n).

    Dopamine uses i = 1 .. n; we follow the paper (i = 0 is a constant feature, a bias)."""
    i = torch.arange(embedding_size, dtype=taus.dtype, device=taus.device)
    return torch.cos(math.pi * taus[..., None] * i)


class ImplicitQuantileNetwork(nn.Module):
    """Z(s, tau) = f(psi(s) * phi(tau)); (B, ...) frames and (B, N) fractions -> (B, N, A)."""

    def __init__(
        self, shape: dc.Shape, num_actions: int, settings: dc.AtariSettings, embedding_size: int
    ) -> None:
        super().__init__()
        self.torso = dc.NatureTorso(shape, settings)
        self.embedding_size = embedding_size
        self.tau_layer = nn.Linear(embedding_size, self.torso.output_size)
        self.head = dc.mlp_head(self.torso.output_size, settings.hidden_size, num_actions)

    def forward(self, frames: torch.Tensor, taus: torch.Tensor) -> torch.Tensor:
        features = self.torso(frames)  # (B, D)
        phi = F.relu(self.tau_layer(cosine_tau_embedding(taus, self.embedding_size)))  # (B, N, D)
        return self.head(features[:, None, :] * phi)


def quantile_huber_loss(
    quantiles: torch.Tensor, taus: torch.Tensor, targets: torch.Tensor, kappa: float = 1.0
) -> torch.Tensor:
    """IQN eq. (3) per batch element: sum_i mean_j rho^kappa_{tau_i}(T_j - Z_i).

    quantiles (B, N) at fractions taus (B, N); targets (B, N') -> (B,). With kappa = 0 the Huber
    part becomes |u| (plain quantile regression)."""
    u = targets[:, None, :] - quantiles[:, :, None]  # (B, N, N')
    weight = (taus[:, :, None] - (u.detach() < 0).float()).abs()
    if kappa > 0:
        elementwise = weight * dc.huber(u, kappa) / kappa
    else:
        elementwise = weight * u.abs()
    return elementwise.mean(2).sum(1)


def _taken_quantiles(quantiles: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """quantiles (B, N, A) at action (B,) -> (B, N)."""
    index = action[:, None, None].expand(-1, quantiles.shape[1], 1)
    return quantiles.gather(-1, index).squeeze(-1)


def iqn_loss(network: ImplicitQuantileNetwork, target_network: ImplicitQuantileNetwork,
             batch: dc.TorchTransition, gamma: float,
             generator: torch.Generator, num_taus: int, num_taus_next: int,
             kappa: float = 1.0,
             double_q: bool = False) -> tuple[torch.Tensor, common.Metrics]:  # fmt: skip
    """Quantile Huber loss between N online quantiles and N' target quantiles. The next action
    is the argmax of the mean of the target quantiles (Acme's IQN learner); with ``double_q`` it
    is the online network's on the same N' fractions."""
    size, device = batch.action.shape[0], batch.action.device
    taus = torch.rand(size, num_taus, generator=generator, device=device)
    quantiles = _taken_quantiles(network(batch.observation, taus), batch.action)
    with torch.no_grad():
        taus_next = torch.rand(size, num_taus_next, generator=generator, device=device)
        next_quantiles = target_network(batch.next_observation, taus_next)  # (B, N', A)
        if double_q:
            selector = network(batch.next_observation, taus_next).mean(1)
        else:
            selector = next_quantiles.mean(1)
        next_taken = _taken_quantiles(next_quantiles, selector.argmax(-1))
        targets = batch.reward[:, None] + gamma * batch.discount[:, None] * next_taken
    loss = quantile_huber_loss(quantiles, taus, targets, kappa).mean()
    return loss, {
        "critic/loss": loss, "critic/q": quantiles.mean(), "critic/target": targets.mean(),
    }  # fmt: skip


class IQNAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: IQNConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.batch_spec, self.num_steps = config.atari.batch_spec(), config.atari.num_steps
        self.pretrain_steps = 0
        self.network, self.target_network, self.optimizers, self.generators = dc.build(
            "iqn", observation_spec, action_spec, config, seed, self.device,
            lambda shape, n, s: ImplicitQuantileNetwork(shape, n, s, config.embedding_size),
        )  # fmt: skip
        self.modules = {"network": self.network, "target_network": self.target_network}
        self.targets = {self.target_network: self.network}  # copied every target_update_period

    def update(self, batch: Transition) -> dict[str, float]:
        c = self.config
        loss, metrics = iqn_loss(
            self.network, self.target_network, dc.to_torch(batch, self.device),
            self.batch_spec.bootstrap_gamma, self.generators["learner"],
            c.num_tau_samples, c.num_tau_samples, c.kappa, c.double_q,
        )  # fmt: skip
        self.step = dc.learn(self.optimizers["network"], loss, self.step, c.atari, self.targets)
        return common.metrics_to_floats(metrics)

    @torch.inference_mode()
    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """argmax_a of the mean of ``num_quantile_samples`` quantiles at fractions drawn from the
        acting generator, epsilon-greedy (``atari.eval_epsilon`` when greedy)."""
        frames, generator = dc.frames(observation, device=self.device), self.generators["act"]
        taus = torch.rand(
            frames.shape[0], self.config.num_quantile_samples, generator=generator,
            device=self.device,
        )  # fmt: skip
        q = self.network(frames, taus).mean(1)
        return dc.epsilon_greedy(q, dc.epsilon(self.config.atari, greedy), generator)

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = IQNAgent
