"""Behaviour cloning for discrete actions (paper appendix A.2; Pomerleau 1989).

The Nature CNN with a 512-unit layer outputs one logit per action, trained with cross-entropy
on the logged actions. The paper evaluates BC with "the max action from the policy head".
Deviations: Adam epsilon 1e-7 (TF2 default, as the paper states); the learning-rate grid is
{3e-5, 5e-5, 1e-4} (see ``discrete_common.LEARNING_RATE_GRID``).

Acting: ``greedy=True`` is argmax_a of the logits (the max action), replaced by a uniform action
with probability ``eval_epsilon`` (0.4^8, the evaluation epsilon the paper's table gives every
Atari baseline; set it to 0 for the pure max action); ``greedy=False`` samples from the softmax
policy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from rlu.agents import discrete_common as dc
from rlu.types import Transition


@dataclass(frozen=True)
class BCConfig:
    learning_rate: float = 3e-5
    """Adam step size; the paper used 3e-5 for BC's offline policy selection."""
    adam_eps: float = 1e-7
    """Adam epsilon: TF2's default, as the paper states."""
    batch_size: int = 256
    """Transitions per update (read by the training loop)."""
    eval_epsilon: float = dc.EVAL_EPSILON
    """Probability of a uniform action when acting greedily (the paper's evaluation epsilon)."""
    num_steps: int = 2_000_000
    """Learner steps of a full run (read by the training loop)."""
    channels: tuple[int, ...] = (32, 64, 64)
    """Nature CNN output channels per convolution."""
    kernel_sizes: tuple[int, ...] = (8, 4, 3)
    """Nature CNN square filter sizes."""
    strides: tuple[int, ...] = (4, 2, 1)
    """Nature CNN strides."""
    hidden_size: int = 512
    """Units of the fully connected layer after the convolutions."""


Config = BCConfig

PRESETS: dict[str, BCConfig] = {
    "paper": BCConfig(),
    "small": BCConfig(**dc.SMALL_SCALE),
}

GRID: dict[str, list[Any]] = {"learning_rate": list(dc.LEARNING_RATE_GRID)}


class BCAgent:
    batch_kind = "transition"
    n_step = 1
    sequence_length = 1

    def __init__(self, observation_spec, action_spec, config: BCConfig, seed: int = 0) -> None:
        shape, num_actions = dc.check_specs("bc", observation_spec, action_spec)
        self.config = config
        init_seed, learner_seed, act_seed = dc.seeds(seed)

        def build() -> dc.QNetwork:
            torso = dc.NatureTorso(shape, config.channels, config.kernel_sizes, config.strides)
            return dc.QNetwork(torso, config.hidden_size, num_actions)

        network = dc.build_seeded(init_seed, build)
        self.learner = dc.SGDLearner.from_config(network, dc.BCLoss(), config, learner_seed)
        self.act_generator = torch.Generator().manual_seed(act_seed)

    def update(self, batch: Transition) -> dict[str, float]:
        return self.learner.step(dc.to_torch(batch))

    @torch.no_grad()
    def act(self, observation: np.ndarray, greedy: bool = True) -> np.ndarray:
        logits = self.learner.network(dc.frames_to_tensor(observation))
        if greedy:
            return dc.epsilon_greedy(logits, self.config.eval_epsilon, self.act_generator)
        sample = torch.multinomial(logits.softmax(-1), 1, generator=self.act_generator)
        return sample.squeeze(-1).numpy().astype(np.int64)

    def state_dict(self) -> dict[str, Any]:
        return dc.agent_state(self.learner, self.act_generator)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        dc.load_agent_state(self.learner, self.act_generator, state)


Agent = BCAgent

__all__ = ["BCConfig", "BCAgent", "Config", "Agent", "PRESETS", "GRID"]
