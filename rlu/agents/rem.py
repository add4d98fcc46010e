"""Random Ensemble Mixture, REM (paper appendix A.2; Agarwal et al. 2020, "An Optimistic
Perspective on Offline Reinforcement Learning").

The paper: "We have used a random ensemble of 4 DQN networks in our implementation", learning
rate 1e-4 from online policy selection. The ``paper`` preset is that: ``num_heads`` = 4
separate Nature CNN Q-networks (convolutions, 512-unit layer and action outputs each), as the
original code's ``MulitNetworkQNetwork`` (google-research/batch_rl,
``batch_rl/multi_head/atari_helpers.py``, used by ``multi_network_dqn_agent.py`` with
``transform_strategy='STOCHASTIC'``). ``separate_networks=False`` gives the multi-head REM of
the same code (``MultiHeadQNetwork``, ``fixed_replay/configs/rem.gin``): one torso and 512-unit
layer shared by ``num_heads`` x actions outputs, about 4x cheaper; the ``small`` preset uses it.

Every update draws one convex combination alpha of the estimates (uniform draws normalised to
sum to one, ``random_stochastic_matrix`` with one column) and regresses the same combination of
the online estimates onto the Q-learning target of that combination of the target estimates:
max over actions, no double-Q (which the paper names for DQN only). Deviations: Adam epsilon
1e-7 (TF2 default, as the paper states) instead of batch_rl's 0.01/32; the learning-rate grid is
{3e-5, 5e-5, 1e-4} (see ``discrete_common.LEARNING_RATE_GRID``).

Acting: ``greedy=True`` is argmax_a of the mean of the estimates (Agarwal et al.'s evaluation),
replaced by a uniform action with probability ``atari.eval_epsilon`` (0.4^8); ``greedy=False``
uses ``atari.explore_epsilon`` (0.01).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents import discrete_common as dc
from rlu.files import LEARNING_RATE, Checked, bounds
from rlu.types import ActionSpec, Observation, ObservationSpec, Transition


@dataclass(frozen=True)
class REMConfig(Checked):
    atari: dc.AtariSettings = field(default_factory=dc.AtariSettings)
    """Settings shared by the Atari baselines (batch, discount, network, epsilons, budget)."""
    learning_rate: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam step size; the paper's online policy selection picked 1e-4 for REM."""
    num_heads: int = field(default=4, metadata=bounds(min=1, max=1024))
    """Q-value estimates mixed by a random convex combination (the paper's 4)."""
    separate_networks: bool = True
    """Each estimate is a Q-network of its own (the paper's "random ensemble of 4 DQN
    networks"); False: ``num_heads`` heads on one shared torso (batch_rl's multi-head REM)."""


Config = REMConfig

PRESETS: dict[str, REMConfig] = {
    "paper": REMConfig(),
    # one shared torso: a quarter of the convolutions' cost on a CPU
    "small": REMConfig(**dc.SMALL_FIELDS, separate_networks=False),
}

GRID: dict[str, list[Any]] = {"learning_rate": list(dc.LEARNING_RATE_GRID)}


class QEnsemble(nn.Module):
    """``num`` separate Q-networks (``discrete_common.QNetwork`` each): (B, num, A) out."""

    def __init__(
        self, shape: dc.Shape, num_actions: int, settings: dc.AtariSettings, num: int
    ) -> None:
        super().__init__()
        self.networks = nn.ModuleList(dc.QNetwork(shape, num_actions, settings) for _ in range(num))

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        return torch.stack([network(frames) for network in self.networks], 1)


def q_estimates(
    shape: dc.Shape, num_actions: int, settings: dc.AtariSettings, config: REMConfig
) -> QEnsemble | dc.QNetwork:
    """REM's network: the ensemble of separate networks, or the multi-head network."""
    if config.separate_networks:
        return QEnsemble(shape, num_actions, settings, config.num_heads)
    return dc.QNetwork(shape, num_actions, settings, config.num_heads)


def random_convex_weights(
    num_heads: int, generator: torch.Generator, device: torch.device | None = None
) -> torch.Tensor:
    """REM's alpha: uniform draws normalised to sum to one (Agarwal et al. 2020, one per batch),
    on ``device`` (None: the generator's)."""
    weights = torch.rand(num_heads, generator=generator, device=device or generator.device)
    return weights / weights.sum()


def rem_loss(network: nn.Module, target_network: nn.Module, batch: dc.TorchTransition,
             gamma: float, alpha: torch.Tensor,
             huber_delta: float = 1.0) -> tuple[torch.Tensor, common.Metrics]:  # fmt: skip
    """Huber loss on one convex combination ``alpha`` of the heads, with the Q-learning (max)
    target of the same combination of the target heads."""
    q = torch.einsum("bka,k->ba", network(batch.observation), alpha)
    q_taken = dc.taken(q, batch.action)
    with torch.no_grad():
        q_next = torch.einsum("bka,k->ba", target_network(batch.next_observation), alpha)
        target = dc.q_learning_target(batch.reward, batch.discount, gamma, q_next)
    loss = dc.huber(target - q_taken, huber_delta).mean()
    return loss, {"critic/loss": loss, "critic/q": q_taken.mean(), "critic/target": target.mean()}


class REMAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: REMConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.batch_spec, self.num_steps = config.atari.batch_spec(), config.atari.num_steps
        self.pretrain_steps = 0
        self.network, self.target_network, self.optimizers, self.generators = dc.build(
            "rem", observation_spec, action_spec, config, seed, self.device,
            lambda shape, n, s: q_estimates(shape, n, s, config),
        )  # fmt: skip
        self.modules = {"network": self.network, "target_network": self.target_network}
        self.targets = {self.target_network: self.network}  # copied every target_update_period

    def update(self, batch: Transition) -> dict[str, float]:
        c = self.config
        alpha = random_convex_weights(c.num_heads, self.generators["learner"], self.device)
        loss, metrics = rem_loss(
            self.network, self.target_network, dc.to_torch(batch, self.device),
            self.batch_spec.bootstrap_gamma, alpha, c.atari.huber_delta,
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
        """argmax_a of the mean of the heads' Q (Agarwal et al.'s evaluation), replaced by a
        uniform action with probability ``atari.eval_epsilon`` (greedy) or ``explore_epsilon``."""
        q = self.network(dc.frames(observation, device=self.device)).mean(1)
        return dc.epsilon_greedy(q, dc.epsilon(self.config.atari, greedy), self.generators["act"])

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = REMAgent
