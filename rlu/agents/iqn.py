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
action with probability ``eval_epsilon`` (0.4^8); ``greedy=False`` uses ``explore_epsilon`` (0.01).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from rlu.agents import discrete_common as dc
from rlu.types import Transition


@dataclass(frozen=True)
class IQNConfig:
    learning_rate: float = 1e-4
    """Adam step size; the paper's online policy selection picked 1e-4 for IQN."""
    adam_eps: float = 1e-7
    """Adam epsilon: TF2's default, as the paper states."""
    batch_size: int = 256
    """Transitions per update (read by the training loop)."""
    discount: float = 0.99
    """gamma of the TD target."""
    target_update_period: int = 2500
    """Updates between hard copies of the online network into the target network."""
    num_tau_samples: int = 16
    """Quantile fractions drawn per transition, for the online (N) and the target (N') side."""
    num_quantile_samples: int = 32
    """Fractions drawn per observation to estimate Q when acting (Dopamine's K)."""
    embedding_size: int = 64
    """Cosine features of tau (n in the IQN paper)."""
    kappa: float = 1.0
    """Where the quantile Huber loss turns linear."""
    double_q: bool = False
    """Select the next action with the online network instead of the target network."""
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


Config = IQNConfig

PRESETS: dict[str, IQNConfig] = {
    "paper": IQNConfig(),
    "small": IQNConfig(
        **dc.SMALL_SCALE,
        target_update_period=dc.SMALL_TARGET_UPDATE_PERIOD,
        num_tau_samples=8,
        num_quantile_samples=8,
        embedding_size=32,
    ),
}

GRID: dict[str, list[Any]] = {
    "learning_rate": list(dc.LEARNING_RATE_GRID),
    "num_tau_samples": [8, 16, 32],
}


def make_loss(config: IQNConfig) -> dc.QuantileLoss:
    return dc.QuantileLoss(
        config.discount**config.n_step,
        config.num_tau_samples,
        config.num_tau_samples,
        config.kappa,
        config.double_q,
    )


class IQNAgent:
    batch_kind = "transition"
    sequence_length = 1

    def __init__(self, observation_spec, action_spec, config: IQNConfig, seed: int = 0) -> None:
        shape, num_actions = dc.check_specs("iqn", observation_spec, action_spec)
        self.config = config
        self.n_step = config.n_step
        init_seed, learner_seed, act_seed = dc.seeds(seed)

        def build() -> dc.ImplicitQuantileNetwork:
            torso = dc.NatureTorso(shape, config.channels, config.kernel_sizes, config.strides)
            return dc.ImplicitQuantileNetwork(
                torso, config.hidden_size, num_actions, config.embedding_size
            )

        network = dc.build_seeded(init_seed, build)
        self.learner = dc.SGDLearner.from_config(network, make_loss(config), config, learner_seed)
        self.act_generator = torch.Generator().manual_seed(act_seed)

    def update(self, batch: Transition) -> dict[str, float]:
        return self.learner.step(dc.to_torch(batch))

    @torch.no_grad()
    def act(self, observation: np.ndarray, greedy: bool = True) -> np.ndarray:
        frames = dc.frames_to_tensor(observation)
        taus = torch.rand(
            frames.shape[0], self.config.num_quantile_samples, generator=self.act_generator
        )
        q = self.learner.network(frames, taus).mean(1)
        epsilon = self.config.eval_epsilon if greedy else self.config.explore_epsilon
        return dc.epsilon_greedy(q, epsilon, self.act_generator)

    def state_dict(self) -> dict[str, Any]:
        return dc.agent_state(self.learner, self.act_generator)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        dc.load_agent_state(self.learner, self.act_generator, state)


Agent = IQNAgent

__all__ = ["IQNConfig", "IQNAgent", "Config", "Agent", "PRESETS", "GRID", "make_loss"]
