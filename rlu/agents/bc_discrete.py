"""Behaviour cloning for discrete actions (paper appendix A.2; Pomerleau 1989).

The Nature CNN with a 512-unit layer outputs one logit per action, trained with cross-entropy
on the logged actions. The paper evaluates BC with "the max action from the policy head".
Deviations: Adam epsilon 1e-7 (TF2 default, as the paper states); the learning-rate grid is
{3e-5, 5e-5, 1e-4} (see ``discrete_common.LEARNING_RATE_GRID``).

Acting: ``greedy=True`` is argmax_a of the logits (the max action), replaced by a uniform action
with probability ``atari.eval_epsilon`` (0.4^8, the evaluation epsilon the paper's table gives
every Atari baseline; set it to 0 for the pure max action); ``greedy=False`` samples from the
softmax policy.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from rlu.agents import common
from rlu.agents import discrete_common as dc
from rlu.files import MAX_LR, Checked, bounds
from rlu.types import Transition


@dataclass(frozen=True)
class BCConfig(Checked):
    atari: dc.AtariSettings = field(default_factory=dc.AtariSettings)
    """Settings shared by the Atari baselines (batch, network, epsilons, budget; BC uses no
    reward, discount or target network)."""
    learning_rate: float = field(default=3e-5, metadata=bounds(gt=0.0, max=MAX_LR))
    """Adam step size; the paper used 3e-5 for BC's offline policy selection."""


Config = BCConfig

PRESETS: dict[str, BCConfig] = {
    "paper": BCConfig(),
    "small": BCConfig(**dc.SMALL_FIELDS),
}

GRID: dict[str, list[Any]] = {"learning_rate": list(dc.LEARNING_RATE_GRID)}


def bc_loss(logits: torch.Tensor, action: torch.Tensor):
    """Cross-entropy of the policy logits on the logged actions."""
    loss = F.cross_entropy(logits, action)
    accuracy = (logits.argmax(-1) == action).float().mean()
    return loss, {"actor/bc_loss": loss, "actor/accuracy": accuracy}


class BCAgent:
    def __init__(
        self, observation_spec, action_spec, config: BCConfig, seed: int = 0, device="cpu"
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.batch_spec, self.num_steps = config.atari.batch_spec(), config.atari.num_steps
        self.pretrain_steps = 0
        self.network, self.target_network, self.optimizers, self.generators = dc.build(
            "bc",
            observation_spec,
            action_spec,
            config,
            seed,
            self.device,
            dc.QNetwork,
            target=False,
        )
        self.modules = {"network": self.network}

    def update(self, batch: Transition) -> dict[str, float]:
        frames = dc.frames(batch.observation, channels_last=True, device=self.device)
        action = common.to_torch(batch.action, self.device, "int64")
        loss, metrics = bc_loss(self.network(frames), action)
        self.step = common.learn(self.optimizers["network"], loss, self.step)
        return common.metrics_to_floats(metrics)

    @torch.inference_mode()
    def act(self, observation, greedy: bool = True, is_first=None, reward=None) -> np.ndarray:
        """The max action of the logits, epsilon-greedy with ``atari.eval_epsilon`` (greedy), or
        a sample of the softmax policy (``greedy=False``)."""
        logits = self.network(dc.frames(observation, device=self.device))
        if greedy:
            return dc.epsilon_greedy(logits, self.config.atari.eval_epsilon, self.generators["act"])
        sample = torch.multinomial(logits.softmax(-1), 1, generator=self.generators["act"])
        return sample.squeeze(-1).cpu().numpy().astype(np.int64)

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = BCAgent
