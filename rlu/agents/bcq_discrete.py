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
head on the same observation), replaced by a uniform action with probability ``eval_epsilon``
(0.4^8); ``greedy=False`` uses ``explore_epsilon`` (0.01), the uniform draw then ignoring the
mask as in the authors' code.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from rlu.agents import discrete_common as dc
from rlu.types import Transition


@dataclass(frozen=True)
class BCQConfig:
    learning_rate: float = 1e-4
    """Adam step size; the paper's online policy selection picked 1e-4 for BCQ."""
    adam_eps: float = 1e-7
    """Adam epsilon: TF2's default, as the paper states."""
    batch_size: int = 256
    """Transitions per update (read by the training loop)."""
    discount: float = 0.99
    """gamma of the TD target."""
    target_update_period: int = 2500
    """Updates between hard copies of the online network into the target network."""
    threshold: float = 0.5
    """Allowed actions have pi(a|s) / max_a' pi(a'|s) >= threshold (paper: 0.5 of the grid)."""
    logit_penalty: float = 1e-2
    """Weight of the mean squared imitation logit in the loss (the authors' value)."""
    huber_delta: float = 1.0
    """Where the Huber loss turns linear."""
    eval_epsilon: float = dc.EVAL_EPSILON
    """Probability of a uniform action when acting greedily (the paper's evaluation epsilon)."""
    explore_epsilon: float = 0.01
    """Probability of a uniform action when acting with greedy=False."""
    num_steps: int = 2_000_000
    """Learner steps of a full run (read by the training loop)."""
    n_step: int = 1
    """Bootstrapping horizon of the batches the training loop samples; the target discounts
    by discount**n_step (the views give the n-step reward sum and discount product)."""
    channels: tuple[int, ...] = (32, 64, 64)
    """Nature CNN output channels per convolution."""
    kernel_sizes: tuple[int, ...] = (8, 4, 3)
    """Nature CNN square filter sizes."""
    strides: tuple[int, ...] = (4, 2, 1)
    """Nature CNN strides."""
    hidden_size: int = 512
    """Units of the fully connected layer after the convolutions."""


Config = BCQConfig

PRESETS: dict[str, BCQConfig] = {
    "paper": BCQConfig(),
    "small": BCQConfig(**dc.SMALL_SCALE, target_update_period=dc.SMALL_TARGET_UPDATE_PERIOD),
}

GRID: dict[str, list[Any]] = {
    "learning_rate": list(dc.LEARNING_RATE_GRID),
    "threshold": [0.25, 0.5, 0.75, 1.0],
}


def make_loss(config: BCQConfig) -> dc.BCQLoss:
    return dc.BCQLoss(
        config.discount**config.n_step, config.threshold, config.huber_delta, config.logit_penalty
    )


class BCQAgent:
    batch_kind = "transition"
    sequence_length = 1

    def __init__(self, observation_spec, action_spec, config: BCQConfig, seed: int = 0) -> None:
        shape, num_actions = dc.check_specs("bcq", observation_spec, action_spec)
        self.config = config
        self.n_step = config.n_step
        init_seed, learner_seed, act_seed = dc.seeds(seed)

        def build() -> dc.QAndPolicyNetwork:
            torso = dc.NatureTorso(shape, config.channels, config.kernel_sizes, config.strides)
            return dc.QAndPolicyNetwork(torso, config.hidden_size, num_actions)

        network = dc.build_seeded(init_seed, build)
        self.learner = dc.SGDLearner.from_config(network, make_loss(config), config, learner_seed)
        self.act_generator = torch.Generator().manual_seed(act_seed)

    def update(self, batch: Transition) -> dict[str, float]:
        return self.learner.step(dc.to_torch(batch))

    @torch.no_grad()
    def act(self, observation: np.ndarray, greedy: bool = True) -> np.ndarray:
        q, logits = self.learner.network(dc.frames_to_tensor(observation))
        allowed = dc.bcq_action_mask(logits, self.config.threshold)
        q = q.masked_fill(~allowed, float("-inf"))
        epsilon = self.config.eval_epsilon if greedy else self.config.explore_epsilon
        return dc.epsilon_greedy(q, epsilon, self.act_generator)

    def state_dict(self) -> dict[str, Any]:
        return dc.agent_state(self.learner, self.act_generator)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        dc.load_agent_state(self.learner, self.act_generator, state)


Agent = BCQAgent

__all__ = ["BCQConfig", "BCQAgent", "Config", "Agent", "PRESETS", "GRID", "make_loss"]
