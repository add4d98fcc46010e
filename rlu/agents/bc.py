"""Behaviour cloning with a Gaussian-mixture policy (paper appendix A.1, "BC").

Paper: Gulcehre et al. 2020, RL Unplugged, appendix A.1 and table 5. The policy is the shared
torso (ResNet for cameras, residual MLP 8 x 1024, two LSTM-1024 layers for the sequence tasks)
followed by a 5-component diagonal Gaussian mixture; it maximises the log-likelihood of the
data's actions with Adam at 1e-4, batch 1024 (128 windows when recurrent).

Deviations and choices:
- Actions are learnt in [-1, 1] (the spec's box rescaled) and clipped into the box in ``act``.
- Acting: ``act(greedy=True)`` is the paper's evaluation policy, a sample of the mixture with
  every component's variance fixed to 1e-4 (``eval_variance``); ``act(greedy=False)`` samples the
  learnt mixture as it is. Both draw from the agent's own acting generator.
- Recurrent windows start from a zero LSTM state; the loss skips padded steps and each
  episode's final step (its action carries no information, RLDS semantics).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents import networks as nets
from rlu.agents.losses import mixture_log_prob
from rlu.files import LEARNING_RATE, STEPS, Checked, bounds
from rlu.seeds import stream_seed
from rlu.types import ActionSpec, BatchSpec, Observation, ObservationSpec, Sequence, Transition


@dataclass(frozen=True)
class BCConfig(Checked):
    hidden_size: int = field(default=1024, metadata=bounds(min=1, max=16384))
    """Width of the residual MLP."""
    num_layers: int = field(default=8, metadata=bounds(min=1, max=64))
    """Layers of the residual MLP (normalised every two)."""
    torso_hidden: int = field(default=64, metadata=bounds(min=1, max=16384))
    """Embedding size of the ResNet camera torso (table 5, ABM & BC column)."""
    mixture_components: int = field(default=5, metadata=bounds(min=1, max=1024))
    """Gaussian components of the policy head."""
    eval_variance: float = field(default=1e-4, metadata=bounds(min=1e-12, max=1e6))
    """Variance of every component when acting greedily (the paper's evaluation, 1e-4)."""
    learning_rate: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam learning rate."""
    batch_size: int = field(default=1024, metadata=bounds(min=1, max=1 << 20))
    """Transitions per update; windows per update when recurrent (the paper: 1024 and 128)."""
    num_steps: int = field(default=1_000_000, metadata=STEPS)
    """Learner steps of a full run: what ``rlu train`` runs when no --steps is given. The paper
    states no budget for the continuous baselines; 1M is rlu's choice."""
    recurrent: bool = False
    """Two LSTM layers after the MLP; trains on sequence windows."""
    lstm_hidden: int = field(default=1024, metadata=bounds(min=1, max=16384))
    """Hidden size of each LSTM layer."""
    sequence_length: int = field(default=40, metadata=bounds(min=1, max=100_000))
    """Window length of recurrent batches."""


Config = BCConfig
PRESETS = {
    "paper": BCConfig(),
    "paper_recurrent": BCConfig(recurrent=True, batch_size=128),  # the sequence tasks
    "small": BCConfig(hidden_size=256, num_layers=2, learning_rate=1e-3, batch_size=256,
                      lstm_hidden=64, sequence_length=10, num_steps=20_000),
}  # fmt: skip
GRID: dict[str, list] = {}  # the paper reports no sweep for BC


def bc_loss(
    logits: torch.Tensor,
    mean: torch.Tensor,
    std: torch.Tensor,
    action: torch.Tensor,
    weight: torch.Tensor | None = None,
) -> tuple[torch.Tensor, common.Metrics]:
    """Negative log-likelihood of the data's actions under the mixture (``weight``: step mask)."""
    log_prob = mixture_log_prob(logits, mean, std, action)
    if weight is None:
        loss = -log_prob.mean()
    else:
        loss = -(log_prob * weight).sum() / weight.sum().clamp(min=1.0)
    return loss, {"actor/bc_loss": loss}


class BCAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: BCConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.scaler = nets.ActionScaler(action_spec)
        kind = "sequence" if config.recurrent else "transition"
        self.batch_spec = BatchSpec(config.batch_size, kind, sequence_length=config.sequence_length)
        self.num_steps, self.pretrain_steps = config.num_steps, 0
        act_seed = stream_seed(seed, "act")
        with common.seeded(seed):
            torso = nets.Torso(
                observation_spec, config.hidden_size, config.num_layers,
                lstm_hidden=config.lstm_hidden if config.recurrent else 0,
                torso_hidden=config.torso_hidden,
            )  # fmt: skip
            head = nets.MixtureHead(torso.output_dim, self.scaler.dim, config.mixture_components)
            self.policy = nn.ModuleDict({"torso": torso, "head": head}).to(self.device)
        self.modules = {"policy": self.policy}
        self.optimizers = {"policy": common.adam(self.policy.parameters(), config.learning_rate)}
        self.generators = {"act": common.generator(act_seed, self.device)}
        self._rollout_state = None

    def update(self, batch: Transition | Sequence) -> dict[str, float]:
        seq = isinstance(batch, Sequence)
        obs = common.to_torch(batch.observation, self.device)
        action = self.scaler.to_unit(common.to_torch(batch.action, self.device))
        weight = None
        if isinstance(batch, Sequence):
            weight = common.to_torch(batch.mask & ~batch.is_last, self.device).float()
        h, _ = self.policy["torso"](obs, sequence=seq)
        logits, mean, std = self.policy["head"](h)
        loss, metrics = bc_loss(logits, mean, std, action, weight)
        self.step = common.learn(self.optimizers["policy"], loss, self.step)
        return common.metrics_to_floats(metrics)

    @torch.inference_mode()
    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """A sample of the mixture with every component's variance ``eval_variance`` (the
        paper's evaluation) with ``greedy=True``; the learnt mixture as is with ``greedy=False``."""
        obs = common.to_torch(observation, self.device)
        state = nets.carried_state(self._rollout_state, is_first, obs)
        h, self._rollout_state = self.policy["torso"](obs, state=state)
        logits, mean, std = self.policy["head"](h)
        sd = self.config.eval_variance**0.5 if greedy else None
        action = nets.mixture_sample(logits, mean, std, self.generators["act"], std_override=sd)
        return self.scaler.from_unit(action)

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)
        self._rollout_state = None  # acting restarts after a restore


Agent = BCAgent
