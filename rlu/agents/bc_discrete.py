"""Behaviour cloning for discrete actions (paper appendix A.2; Pomerleau 1989).

The Nature CNN with a 512-unit layer outputs one logit per action, trained with cross-entropy
on the logged actions. The paper evaluates BC with "the max action from the policy head".
Deviations: Adam epsilon 1e-7 (TF2 default, as the paper states); the learning-rate grid is
{3e-5, 5e-5, 1e-4} (see ``discrete_common.LEARNING_RATE_GRID``).

Acting: ``greedy=True`` is argmax_a of the logits (the max action), replaced by a uniform action
with probability ``atari.eval_epsilon`` (0.4^8, the evaluation epsilon the paper's table gives
every Atari baseline; set it to 0 for the pure max action); ``greedy=False`` samples from the
softmax policy.

Recurrent (``recurrent=True``, beyond the paper: the memory DeepMind Lab's levels ask for, as in
the R2D2 agent that recorded them): the torso's features go through a hidden layer and an LSTM
(``discrete_common.RecurrentCore``) before the logits, and the loss is over windows of
``sequence_length`` steps unrolled from a zero state, skipping padded steps and each episode's
final step (its action carries no information, RLDS semantics), as the continuous BC does.
Acting keeps every row's LSTM state, reset where ``is_first``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from rlu.agents import common
from rlu.agents import discrete_common as dc
from rlu.agents import networks as nets
from rlu.files import LEARNING_RATE, Checked, bounds
from rlu.types import ActionSpec, BatchSpec, Observation, ObservationSpec, Sequence, Transition


@dataclass(frozen=True)
class BCConfig(Checked):
    atari: dc.AtariSettings = field(default_factory=dc.AtariSettings)
    """Settings shared by the Atari baselines (batch, network, epsilons, budget; BC uses no
    reward, discount or target network)."""
    learning_rate: float = field(default=3e-5, metadata=LEARNING_RATE)
    """Adam step size; the paper used 3e-5 for BC's offline policy selection."""
    recurrent: bool = False
    """An LSTM after the torso; trains on sequence windows (module docstring)."""
    lstm_size: int = field(default=512, metadata=bounds(min=1, max=16384))
    """LSTM units when recurrent (R2D2's 512)."""
    sequence_length: int = field(default=80, metadata=bounds(min=1, max=100_000))
    """Window length of recurrent batches (R2D2's 80)."""


Config = BCConfig

PRESETS: dict[str, BCConfig] = {
    "paper": BCConfig(),
    "small": BCConfig(**dc.SMALL_FIELDS),
}

GRID: dict[str, list[Any]] = {"learning_rate": list(dc.LEARNING_RATE_GRID)}


def bc_loss(
    logits: torch.Tensor, action: torch.Tensor, weight: torch.Tensor | None = None
) -> tuple[torch.Tensor, common.Metrics]:
    """Cross-entropy of the policy logits on the logged actions (``weight``: a step mask)."""
    if weight is None:
        loss = F.cross_entropy(logits, action)
        accuracy = (logits.argmax(-1) == action).float().mean()
    else:
        count = weight.sum().clamp(min=1.0)
        loss = (F.cross_entropy(logits, action, reduction="none") * weight).sum() / count
        accuracy = ((logits.argmax(-1) == action).float() * weight).sum() / count
    return loss, {"actor/bc_loss": loss, "actor/accuracy": accuracy}


class RecurrentPolicy(nn.Module):
    """``discrete_common.RecurrentCore`` -> one logit per action; (B, T, A) and the state."""

    def __init__(self, shape: dc.Shape, num_actions: int, settings: dc.AtariSettings,
                 lstm_size: int) -> None:  # fmt: skip
        super().__init__()
        self.core = dc.RecurrentCore(shape, settings, lstm_size)
        self.logits = nn.Linear(lstm_size, num_actions)

    def forward(
        self, frames: Any, batch: int, steps: int, state: common.LSTMState | None = None
    ) -> tuple[torch.Tensor, common.LSTMState]:
        out, state = self.core(frames, batch, steps, state)
        return self.logits(out), state


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
        self.batch_spec, self.num_steps = config.atari.batch_spec(), config.atari.num_steps
        if config.recurrent:
            self.batch_spec = BatchSpec(config.atari.batch_size, "sequence",
                                        sequence_length=config.sequence_length)  # fmt: skip
        self.pretrain_steps = 0

        def recurrent(
            shape: dc.Shape, num_actions: int, settings: dc.AtariSettings
        ) -> RecurrentPolicy:
            return RecurrentPolicy(shape, num_actions, settings, config.lstm_size)

        self.network, self.target_network, self.optimizers, self.generators = dc.build(
            "bc",
            observation_spec,
            action_spec,
            config,
            seed,
            self.device,
            recurrent if config.recurrent else dc.QNetwork,
            target=False,
        )
        self.modules = {"network": self.network}
        self._state: common.LSTMState | None = None  # acting's LSTM state (recurrent)

    def update(self, batch: Transition | Sequence) -> dict[str, float]:
        action = common.to_torch(batch.action, self.device, "int64")
        if isinstance(batch, Sequence):
            b, t = action.shape
            steps = dc.time_steps(batch.observation, 0, t)
            frames = dc.frames(steps, channels_last=True, device=self.device)
            logits, _ = self.network(frames, b, t)
            weight = common.to_torch(batch.mask & ~batch.is_last, self.device).float()
            loss, metrics = bc_loss(logits.reshape(b * t, -1), action.reshape(-1),
                                    weight.reshape(-1))  # fmt: skip
        else:
            frames = dc.frames(batch.observation, channels_last=True, device=self.device)
            loss, metrics = bc_loss(self.network(frames), action)
        self.step = common.learn(self.optimizers["network"], loss, self.step)
        return common.metrics_to_floats(metrics)

    def _logits(self, observation: Observation, is_first: np.ndarray | None) -> torch.Tensor:
        x = dc.frames(observation, device=self.device)
        if not self.config.recurrent:
            return self.network(x)
        n = (x["pixels"] if isinstance(x, dict) else x).shape[0]
        state = nets.carried_state(self._state, is_first, x)
        logits, self._state = self.network(x, n, 1, state)
        return logits[:, 0]

    @torch.inference_mode()
    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """The max action of the logits, epsilon-greedy with ``atari.eval_epsilon`` (greedy), or
        a sample of the softmax policy (``greedy=False``)."""
        logits = self._logits(observation, is_first)
        if greedy:
            return dc.epsilon_greedy(logits, self.config.atari.eval_epsilon, self.generators["act"])
        sample = torch.multinomial(logits.softmax(-1), 1, generator=self.generators["act"])
        return sample.squeeze(-1).cpu().numpy().astype(np.int64)

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)
        self._state = None  # acting restarts after a restore


Agent = BCAgent
