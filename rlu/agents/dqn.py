"""Offline DQN with double-Q targets and Adam (paper appendix A.2; Mnih et al. 2015,
van Hasselt et al. 2016; Agarwal et al. 2020 for offline DQN with Adam).

Original code: Dopamine's ``DQNAgent`` and the batch_rl fixed-replay runner. Deviations:
- Adam with TF2's default epsilon (1e-7) as the paper states, not Dopamine's 0.01/32.
- Huber loss (delta 1) on the double-Q target, as in Dopamine and Acme.
- The paper's learning-rate grid lists 5e-5 twice and omits the 3e-5 it picks for DQN; ``GRID``
  holds {3e-5, 5e-5, 1e-4} (see ``discrete_common.LEARNING_RATE_GRID``).

Acting: ``greedy=True`` is the paper's evaluation policy, argmax_a Q(s, a) replaced by a uniform
action with probability ``atari.eval_epsilon`` (0.4^8); ``greedy=False`` uses
``atari.explore_epsilon`` (0.01, the online agent's training epsilon).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents import discrete_common as dc
from rlu.files import LEARNING_RATE, Checked
from rlu.types import ActionSpec, Observation, ObservationSpec, Transition


@dataclass(frozen=True)
class DQNConfig(Checked):
    atari: dc.AtariSettings = field(default_factory=dc.AtariSettings)
    """Settings shared by the Atari baselines (batch, discount, network, epsilons, budget)."""
    learning_rate: float = field(default=3e-5, metadata=LEARNING_RATE)
    """Adam step size; the paper's online policy selection picked 3e-5 for offline DQN."""
    double_q: bool = True
    """Select the next action with the online network (double DQN), as the paper's offline DQN."""


Config = DQNConfig

PRESETS: dict[str, DQNConfig] = {
    "paper": DQNConfig(),
    "small": DQNConfig(**dc.SMALL_FIELDS),
}

GRID: dict[str, list[Any]] = {"learning_rate": list(dc.LEARNING_RATE_GRID)}


def dqn_loss(network: nn.Module, target_network: nn.Module, batch: dc.TorchTransition,
             gamma: float, huber_delta: float = 1.0,
             double_q: bool = True) -> tuple[torch.Tensor, common.Metrics]:  # fmt: skip
    """Huber loss between Q(s, a) and the (double-)Q target; ``gamma`` bootstraps (gamma^n)."""
    q_taken = dc.taken(network(batch.observation), batch.action)
    target = dc.dqn_target(network, target_network, batch, gamma, double_q)
    loss = dc.huber(target - q_taken, huber_delta).mean()
    return loss, {"critic/loss": loss, "critic/q": q_taken.mean(), "critic/target": target.mean()}


class DQNAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: DQNConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.batch_spec, self.num_steps = config.atari.batch_spec(), config.atari.num_steps
        self.pretrain_steps = 0
        self.network, self.target_network, self.optimizers, self.generators = dc.build(
            "dqn", observation_spec, action_spec, config, seed, self.device, dc.QNetwork
        )
        self.modules = {"network": self.network, "target_network": self.target_network}
        self.targets = {self.target_network: self.network}  # copied every target_update_period

    def update(self, batch: Transition) -> dict[str, float]:
        c = self.config
        loss, metrics = dqn_loss(
            self.network, self.target_network, dc.to_torch(batch, self.device),
            self.batch_spec.bootstrap_gamma, c.atari.huber_delta, c.double_q,
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
        """Epsilon-greedy on Q: argmax_a Q(s, a), replaced by a uniform action with probability
        ``atari.eval_epsilon`` (greedy) or ``atari.explore_epsilon`` (module docstring)."""
        return dc.act(self.network, observation, self.config.atari, greedy, self.generators["act"])

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = DQNAgent
