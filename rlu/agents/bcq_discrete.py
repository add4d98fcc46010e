"""Discrete batch-constrained Q-learning, BCQ (paper appendix A.2; Fujimoto et al. 2019,
"Benchmarking Batch Deep Reinforcement Learning Algorithms").

Original code: sfujim/BCQ ``discrete_BCQ``: one network with a shared Nature CNN torso, a Q head
and an imitation (behaviour) head; the target's next action is the argmax of the online Q over
the actions with pi(a|s) / max pi >= threshold, valued by the target network; the loss adds the
imitation cross-entropy and 1e-2 times the mean squared imitation logit.
Deviations: '>=' instead of the authors' '>' in the mask, so the paper's grid value 1.0 keeps
the behaviour argmax instead of masking every action; Adam epsilon 1e-7 (TF2 default, as the
paper states); the learning-rate grid is {3e-5, 5e-5, 1e-4} (see ``LEARNING_RATE_GRID``).
At threshold 0 the target is exactly double DQN's.

Acting: ``greedy=True`` is argmax_a Q(s, a) over the allowed actions (mask from the imitation
head on the same observation), replaced by a uniform action with probability
``atari.eval_epsilon`` (0.4^8); ``greedy=False`` uses ``atari.explore_epsilon`` (0.01), the
uniform draw then ignoring the mask as in the authors' code.
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
from rlu.files import FRACTION, LEARNING_RATE, Checked, bounds
from rlu.types import ActionSpec, Observation, ObservationSpec, Transition


@dataclass(frozen=True)
class BCQConfig(Checked):
    atari: dc.AtariSettings = field(default_factory=dc.AtariSettings)
    """Settings shared by the Atari baselines (batch, discount, network, epsilons, budget)."""
    learning_rate: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam step size; the paper's online policy selection picked 1e-4 for BCQ."""
    threshold: float = field(default=0.5, metadata=FRACTION)
    """Allowed actions have pi(a|s) / max_a' pi(a'|s) >= threshold (paper: 0.5 of the grid)."""
    logit_penalty: float = field(default=1e-2, metadata=bounds(min=0.0, max=1e6))
    """Weight of the mean squared imitation logit in the loss (the authors' value)."""


Config = BCQConfig

PRESETS: dict[str, BCQConfig] = {
    "paper": BCQConfig(),
    "small": BCQConfig(**dc.SMALL_FIELDS),
}

GRID: dict[str, list[Any]] = {
    "learning_rate": list(dc.LEARNING_RATE_GRID),
    "threshold": [0.25, 0.5, 0.75, 1.0],
}


class QAndPolicyNetwork(nn.Module):
    """Shared Nature torso, a Q head and an imitation logits head."""

    def __init__(self, shape: dc.Shape, num_actions: int, settings: dc.AtariSettings) -> None:
        super().__init__()
        self.torso = dc.NatureTorso(shape, settings)
        self.q_head = dc.mlp_head(self.torso.output_size, settings.hidden_size, num_actions)
        self.policy_head = dc.mlp_head(self.torso.output_size, settings.hidden_size, num_actions)

    def forward(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        features = self.torso(frames)
        return self.q_head(features), self.policy_head(features)


def bcq_action_mask(logits: torch.Tensor, threshold: float) -> torch.Tensor:
    """Allowed actions: pi(a|s) / max_a' pi(a'|s) >= threshold.

    Threshold 0 allows every action (DQN), threshold 1 only the behaviour model's argmax.
    Fujimoto's code uses a strict '>', which at the paper's grid value 1.0 would mask every
    action; '>=' keeps 1.0 meaningful. Computed in log space, so no probability underflows."""
    if threshold <= 0:
        return torch.ones_like(logits, dtype=torch.bool)
    log_ratio = logits - logits.max(-1, keepdim=True).values  # log pi(a) - log max pi
    return log_ratio >= math.log(threshold)


def bcq_loss(
    network: QAndPolicyNetwork,
    target_network: QAndPolicyNetwork,
    batch: dc.TorchTransition,
    gamma: float,
    threshold: float = 0.5,
    huber_delta: float = 1.0,
    logit_penalty: float = 1e-2,
) -> tuple[torch.Tensor, common.Metrics]:
    """Double-Q target restricted to the allowed actions, plus the imitation head's
    cross-entropy and ``logit_penalty`` times its mean squared logit."""
    q, logits = network(batch.observation)
    q_taken = dc.taken(q, batch.action)
    with torch.no_grad():
        q_next_online, logits_next = network(batch.next_observation)
        q_next_target, _ = target_network(batch.next_observation)
        allowed = bcq_action_mask(logits_next, threshold)
        best = q_next_online.masked_fill(~allowed, float("-inf")).argmax(-1)
        target = batch.reward + gamma * batch.discount * dc.taken(q_next_target, best)
    q_loss = dc.huber(target - q_taken, huber_delta).mean()
    bc_loss = F.cross_entropy(logits, batch.action)
    loss = q_loss + bc_loss + logit_penalty * logits.pow(2).mean()
    return loss, {
        "critic/loss": q_loss, "critic/q": q_taken.mean(), "critic/target": target.mean(),
        "actor/bc_loss": bc_loss,
    }  # fmt: skip


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
        self.batch_spec, self.num_steps = config.atari.batch_spec(), config.atari.num_steps
        self.pretrain_steps = 0
        self.network, self.target_network, self.optimizers, self.generators = dc.build(
            "bcq", observation_spec, action_spec, config, seed, self.device, QAndPolicyNetwork
        )
        self.modules = {"network": self.network, "target_network": self.target_network}
        self.targets = {self.target_network: self.network}  # copied every target_update_period

    def update(self, batch: Transition) -> dict[str, float]:
        c = self.config
        loss, metrics = bcq_loss(
            self.network, self.target_network, dc.to_torch(batch, self.device),
            self.batch_spec.bootstrap_gamma, c.threshold, c.atari.huber_delta, c.logit_penalty,
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
        """argmax_a Q(s, a) over the actions the imitation head allows on the same observation,
        epsilon-greedy; the uniform draw ignores the mask, as in the authors' code."""
        q, logits = self.network(dc.frames(observation, device=self.device))
        q = q.masked_fill(~bcq_action_mask(logits, self.config.threshold), float("-inf"))
        return dc.epsilon_greedy(q, dc.epsilon(self.config.atari, greedy), self.generators["act"])

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = BCQAgent
