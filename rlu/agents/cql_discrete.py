"""Conservative Q-learning for Atari, CQL(H) on offline double DQN (Kumar et al. 2020,
"Conservative Q-Learning for Offline Reinforcement Learning": its CQL(H) variant, run on Atari).

The loss is the TD loss of the Q-learner plus ``alpha`` times the CQL(H) regulariser,

    alpha * E_{s ~ D} [ log sum_a exp Q(s, a) - E_{a ~ D} Q(s, a) ],

which pushes down a soft maximum of Q over every action and pushes up Q at the logged action,
so actions the data never took cannot look better than the ones it did. The conservative term
has no target network and no stop-gradient: it trains the same Q(s, .) the TD loss trains.

Original code: github.com/aviralkumar2907/CQL, ``atari/batch_rl/multi_head/quantile_agent.py``
(CQL added to Dopamine/batch_rl's QR-DQN; ``minq_weight`` is alpha). Its regulariser reads
``q_values``, the mean of the 200 quantiles, with the batch mean taken over the logsumexp and
over the taken Q separately, exactly as here. What this file does differently, and why:
- The base learner is double DQN with a Huber loss on Q (rlu's ``dqn``), not QR-DQN. The
  regulariser is the same term on the same Q(s, a); only the TD part differs (quantile Huber
  over 200 quantiles there). RL Unplugged's Atari baselines are DQN-family agents on the Nature
  CNN, so the DQN base makes CQL comparable with ``dqn`` in one controlled change (alpha = 0 is
  ``dqn``, tested), and it is the discrete CQL peers implement (d3rlpy's ``DiscreteCQL`` is
  the same maths: double DQN + Huber + alpha (logsumexp - Q(s, a_data))). The authors' QR-DQN
  target takes the target network's own argmax; ``double_q=False`` gives that target.
- alpha = 1.0: ``minq_weight`` in the authors' released Atari configs (``quantile*.gin``) and
  in their README's command for the 1% data (the README says to adjust it for the 10% and
  first-20M-samples data) but ships no grid, so ``GRID`` holds RL Unplugged's
  learning-rate grid only. alpha acts against the scale of Q: on a task with values below 1
  it must be smaller (tests/agents/test_learning_discrete.py measures why).
- The shared settings are RL Unplugged's Atari table (``discrete_common.AtariSettings``:
  batch 256, Adam epsilon 1e-7, hard target copies every 2500 updates, 2M updates, rewards
  clipped to [-1, 1]) rather than the authors' Dopamine settings (batch 32, Adam epsilon
  3.125e-4, target copies every 2000 updates), so CQL runs on the footing of the other Atari
  baselines of the benchmark. The learning rate keeps the authors' 5e-5, which lies in RL
  Unplugged's grid.

Acting: ``greedy=True`` is argmax_a Q(s, a) replaced by a uniform action with probability
``atari.eval_epsilon`` (0.4^8, the paper's evaluation epsilon); ``greedy=False`` uses
``atari.explore_epsilon`` (0.01).
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
class DiscreteCQLConfig(Checked):
    atari: dc.AtariSettings = field(default_factory=dc.AtariSettings)
    """Settings shared by the Atari baselines (batch, discount, network, epsilons, budget)."""
    learning_rate: float = field(default=5e-5, metadata=LEARNING_RATE)
    """Adam step size: the CQL authors' Atari value, one of RL Unplugged's grid."""
    alpha: float = field(default=1.0, metadata=bounds(min=0.0, max=1e6))
    """Weight of the CQL(H) regulariser (the authors' ``minq_weight``); 0 gives double DQN."""
    double_q: bool = True
    """Select the next action with the online network (double DQN); False takes the target
    network's own argmax, as the authors' QR-DQN base does."""


Config = DiscreteCQLConfig

PRESETS: dict[str, DiscreteCQLConfig] = {
    "paper": DiscreteCQLConfig(),
    "small": DiscreteCQLConfig(**dc.SMALL_FIELDS),
}

GRID: dict[str, list[Any]] = {"learning_rate": list(dc.LEARNING_RATE_GRID)}


def conservative_penalty(q: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """CQL(H)'s regulariser on Q (B, A) at the logged actions (B,): the batch mean of
    logsumexp_a Q(s, a) - Q(s, a_data). It is positive (logsumexp > max >= Q(s, a_data)) and
    falls towards 0 as Q(s, a_data) rises above the other actions' values."""
    return (torch.logsumexp(q, -1) - dc.taken(q, action)).mean()


def cql_loss(network: nn.Module, target_network: nn.Module, batch: dc.TorchTransition,
             gamma: float, alpha: float, huber_delta: float = 1.0,
             double_q: bool = True) -> tuple[torch.Tensor, common.Metrics]:  # fmt: skip
    """Huber TD loss to the (double-)Q target plus ``alpha`` x :func:`conservative_penalty`;
    ``gamma`` bootstraps (gamma^n)."""
    q = network(batch.observation)
    q_taken = dc.taken(q, batch.action)
    target = dc.dqn_target(network, target_network, batch, gamma, double_q)
    td_loss = dc.huber(target - q_taken, huber_delta).mean()
    penalty = conservative_penalty(q, batch.action)
    loss = td_loss + alpha * penalty
    return loss, {
        "critic/loss": loss,
        "critic/td_loss": td_loss,
        "critic/conservative_penalty": penalty,
        "critic/q": q_taken.mean(),
        "critic/target": target.mean(),
    }


class DiscreteCQLAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: DiscreteCQLConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.batch_spec, self.num_steps = config.atari.batch_spec(), config.atari.num_steps
        self.pretrain_steps = 0
        self.network, self.target_network, self.optimizers, self.generators = dc.build(
            "cql", observation_spec, action_spec, config, seed, self.device, dc.QNetwork
        )
        self.modules = {"network": self.network, "target_network": self.target_network}
        self.targets = {self.target_network: self.network}  # copied every target_update_period

    def update(self, batch: Transition) -> dict[str, float]:
        c = self.config
        loss, metrics = cql_loss(
            self.network, self.target_network, dc.to_torch(batch, self.device),
            self.batch_spec.bootstrap_gamma, c.alpha, c.atari.huber_delta, c.double_q,
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
        """Epsilon-greedy on the conservative Q, as ``dqn`` acts: argmax_a Q(s, a), or a uniform
        action with probability ``atari.eval_epsilon`` (greedy) or ``atari.explore_epsilon``."""
        return dc.act(self.network, observation, self.config.atari, greedy, self.generators["act"])

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = DiscreteCQLAgent
