"""Offline DQN with double-Q targets and Adam (paper appendix A.2; Mnih et al. 2015,
van Hasselt et al. 2016; Agarwal et al. 2020 for offline DQN with Adam).

Original code: Dopamine's ``DQNAgent`` and the batch_rl fixed-replay runner. Deviations:
- Adam with TF2's default epsilon (1e-7) as the paper states, not Dopamine's 0.01/32.
- Huber loss (delta 1) on the double-Q target, as in Dopamine and Acme.
- The paper's learning-rate grid lists 5e-5 twice and omits the 3e-5 it picks for DQN; ``GRID``
  holds {3e-5, 5e-5, 1e-4} (see ``discrete_common.LEARNING_RATE_GRID``).

Acting: ``greedy=True`` is the paper's evaluation policy, argmax_a Q(s, a) replaced by a uniform
action with probability ``eval_epsilon`` (0.4^8); ``greedy=False`` uses ``explore_epsilon``
(0.01, the online agent's training epsilon).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from rlu.agents import discrete_common as dc
from rlu.types import Transition


@dataclass(frozen=True)
class DQNConfig:
    learning_rate: float = 3e-5
    """Adam step size; the paper's online policy selection picked 3e-5 for offline DQN."""
    adam_eps: float = 1e-7
    """Adam epsilon: TF2's default, as the paper states."""
    batch_size: int = 256
    """Transitions per update (read by the training loop)."""
    discount: float = 0.99
    """gamma of the TD target."""
    target_update_period: int = 2500
    """Updates between hard copies of the online network into the target network."""
    double_q: bool = True
    """Select the next action with the online network (double DQN), as the paper's offline DQN."""
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


Config = DQNConfig

PRESETS: dict[str, DQNConfig] = {
    "paper": DQNConfig(),
    "small": DQNConfig(**dc.SMALL_SCALE, target_update_period=dc.SMALL_TARGET_UPDATE_PERIOD),
}

GRID: dict[str, list[Any]] = {"learning_rate": list(dc.LEARNING_RATE_GRID)}


def make_loss(config: DQNConfig) -> dc.DoubleQLoss:
    return dc.DoubleQLoss(config.discount**config.n_step, config.huber_delta, config.double_q)


class DQNAgent:
    batch_kind = "transition"
    sequence_length = 1

    def __init__(self, observation_spec, action_spec, config: DQNConfig, seed: int = 0) -> None:
        shape, num_actions = dc.check_specs("dqn", observation_spec, action_spec)
        self.config = config
        self.n_step = config.n_step
        init_seed, learner_seed, act_seed = dc.seeds(seed)

        def build() -> dc.QNetwork:
            torso = dc.NatureTorso(shape, config.channels, config.kernel_sizes, config.strides)
            return dc.QNetwork(torso, config.hidden_size, num_actions)

        network = dc.build_seeded(init_seed, build)
        self.learner = dc.SGDLearner.from_config(network, make_loss(config), config, learner_seed)
        self.act_generator = torch.Generator().manual_seed(act_seed)

    def update(self, batch: Transition) -> dict[str, float]:
        return self.learner.step(dc.to_torch(batch))

    @torch.no_grad()
    def act(self, observation: np.ndarray, greedy: bool = True) -> np.ndarray:
        q = self.learner.network(dc.frames_to_tensor(observation))
        epsilon = self.config.eval_epsilon if greedy else self.config.explore_epsilon
        return dc.epsilon_greedy(q, epsilon, self.act_generator)

    def state_dict(self) -> dict[str, Any]:
        return dc.agent_state(self.learner, self.act_generator)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        dc.load_agent_state(self.learner, self.act_generator, state)


Agent = DQNAgent

__all__ = ["DQNConfig", "DQNAgent", "Config", "Agent", "PRESETS", "GRID", "make_loss"]
