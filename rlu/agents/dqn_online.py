"""Dopamine's online DQN: the agent that generated the DQN Replay data behind RL Unplugged's Atari
datasets (paper section "Atari 2600"; Agarwal et al. 2020; Castro et al. 2018, Dopamine).

Original code: google/dopamine ``dopamine/agents/dqn/dqn_agent.py`` with
``dopamine/agents/dqn/configs/dqn.gin``, the default DQN config and the one with sticky actions
(0.25, Machado et al. 2018) that Agarwal et al. ran for 5 runs x 50M agent steps per game.
(``dqn_nature.gin`` is another config: no sticky actions, 50k warm-up, target every 10k steps,
epsilon 0.1/0.05 over 1M steps.) From ``dqn.gin``:

- Nature CNN (32, 64, 64 / 8, 4, 3 / 4, 2, 1, 512 units), batch 32, gamma 0.99, 1-step targets
  (``update_horizon = 1``), rewards clipped to [-1, 1] (Dopamine's runner clips them);
- Huber loss (``tf.losses.huber_loss``, delta 1) against r + gamma d max_a Q_target(s', a):
  **no double Q** (the target network both selects and values the next action);
- ``tf.train.RMSPropOptimizer(learning_rate=0.00025, decay=0.95, momentum=0.0, epsilon=0.00001,
  centered=True)``;
- ``target_update_period = 8000`` agent steps with ``update_period = 4``: a hard copy every
  2000 learner updates (rlu counts the period in updates);
- ``epsilon_train = 0.01`` (``greedy=False``), ``epsilon_eval = 0.001`` (``greedy=True``).
The rest of ``dqn.gin`` (``min_replay_history = 20000``, ``update_period = 4``, epsilon 1 -> 0.01
over ``epsilon_decay_period = 250000`` agent steps, 1M replay, 50M agent steps per run) belongs to
the online loop: the Atari scales of ``rlu generate`` (``rlu.generate.scales``) carry them.

Against rlu's offline ``dqn`` (``dqn.py``, the paper's baseline), this agent differs in exactly
two things besides the settings above: no double Q, and TF1's centered RMSProp instead of Adam.

**RMSProp, TF1 against PyTorch.** TF1's ``ApplyCenteredRMSProp`` (tensorflow/python/training/
rmsprop.py and its kernel), per parameter, with rho = decay:

    ms  <- rho ms + (1 - rho) g^2          (ms starts at 1: TF1 initialises the "rms" slot to ones)
    mg  <- rho mg + (1 - rho) g            (mg starts at 0)
    mom <- momentum mom + lr g / sqrt(ms - mg^2 + eps)
    w   <- w - mom

``torch.optim.RMSprop(centered=True)`` instead divides by ``sqrt(ms - mg^2) + eps`` (epsilon
*outside* the square root) and starts ms at 0. With Dopamine's eps = 1e-5 the two are not a
renaming: TF's floor on the denominator is sqrt(1e-5) = 3.16e-3, torch's would be 1e-5, so a
parameter whose gradient barely varies would take steps up to 316x larger in torch; and TF's
ms = 1 start makes the first ~100 updates (0.95^100 = 0.006) small where torch's first update
divides by |g| sqrt(0.0475) and moves every weight by about 4.6 lr. No choice of torch's eps
reproduces both, so :class:`TFRMSProp` below implements TF1's formula itself (foreach ops, one
kernel per operation over all parameters); ``tests/agents/test_dqn_online.py`` checks one step
against the formula by hand. ``atari.adam_eps`` is unused by this agent.

Deviations: none in the learner. Dopamine keeps epsilon at 1 for the ``min_replay_history``
warm-up and then decays it over 250k steps; rlu's online loop decays it from the first step (see
``rlu.generate.online``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents import discrete_common as dc
from rlu.files import FRACTION, LEARNING_RATE, Checked, bounds
from rlu.types import ActionSpec, Observation, ObservationSpec, Transition

DOPAMINE_ATARI = dc.AtariSettings(
    batch_size=32,  # dqn.gin: WrappedReplayBuffer.batch_size = 32
    gamma=0.99,  # dqn.gin: DQNAgent.gamma = 0.99
    n_step=1,  # dqn.gin: DQNAgent.update_horizon = 1
    reward_clip=1.0,  # Dopamine's runner: np.clip(reward, -1, 1)
    eval_epsilon=0.001,  # dqn.gin: DQNAgent.epsilon_eval = 0.001
    explore_epsilon=0.01,  # dqn.gin: DQNAgent.epsilon_train = 0.01
    target_update_period=2_000,  # dqn.gin: target_update_period 8000 agent steps / update_period 4
    huber_delta=1.0,  # dqn_agent.py: tf.losses.huber_loss, default delta 1
    # dqn.gin: Runner.num_iterations 200 x training_steps 250k = 50M agent steps, one update per 4
    num_steps=12_500_000,
)
"""Dopamine's DQN settings (``dqn.gin``) in the Atari family's settings; the network is the
Nature CNN, AtariSettings' default."""


@dataclass(frozen=True)
class DopamineDQNConfig(Checked):
    atari: dc.AtariSettings = field(default_factory=lambda: DOPAMINE_ATARI)
    """Batch, discount, network, epsilons, target period (in updates), budget: Dopamine's."""
    learning_rate: float = field(default=2.5e-4, metadata=LEARNING_RATE)
    """RMSProp step size (dqn.gin: tf.train.RMSPropOptimizer.learning_rate = 0.00025)."""
    rmsprop_decay: float = field(default=0.95, metadata=FRACTION)
    """Decay of RMSProp's moving averages (dqn.gin: decay = 0.95)."""
    rmsprop_momentum: float = field(default=0.0, metadata=bounds(min=0.0, lt=1.0))
    """RMSProp momentum (dqn.gin: momentum = 0.0)."""
    rmsprop_epsilon: float = field(default=1e-5, metadata=FRACTION)
    """Added to the variance estimate *inside* the square root, as TF1 does (dqn.gin:
    epsilon = 0.00001); see the module docstring for why this is not torch's eps."""
    centered: bool = True
    """Normalise by the gradient's estimated variance rather than its second moment (dqn.gin:
    centered = True)."""


Config = DopamineDQNConfig

PRESETS: dict[str, DopamineDQNConfig] = {
    "paper": DopamineDQNConfig(),
    # the family's small network and budget, Dopamine's epsilons and optimiser
    "small": DopamineDQNConfig(atari=dataclasses.replace(dc.SMALL, eval_epsilon=0.001)),
}

GRID: dict[str, list[Any]] = {}
"""Dopamine's DQN was not swept in the paper: it generated the data."""


class TFRMSProp(torch.optim.Optimizer):
    """TF1's ``tf.train.RMSPropOptimizer`` (dense update, see the module docstring): epsilon
    inside the square root, the mean square started at 1, plain (non-Nesterov) momentum."""

    def __init__(
        self,
        params: Iterable[torch.Tensor],
        lr: float,
        decay: float,
        momentum: float,
        epsilon: float,
        centered: bool,
    ) -> None:
        defaults = dict(lr=lr, decay=decay, momentum=momentum, epsilon=epsilon, centered=centered)
        super().__init__(params, defaults)

    @torch.no_grad()
    def step(self, closure: Callable[[], Any] | None = None) -> Any:
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            params = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            for p in params:
                if not self.state[p]:  # TF1's slots: "rms" ones, "mg" and "momentum" zeros
                    self.state[p].update(
                        rms=torch.ones_like(p), mg=torch.zeros_like(p), momentum=torch.zeros_like(p)
                    )
            grads = [p.grad for p in params]
            rms = [self.state[p]["rms"] for p in params]
            mom = [self.state[p]["momentum"] for p in params]
            # ms += (g^2 - ms)(1 - rho), the kernel's form of rho ms + (1 - rho) g^2
            torch._foreach_lerp_(rms, torch._foreach_mul(grads, grads), 1.0 - group["decay"])
            if group["centered"]:
                mg = [self.state[p]["mg"] for p in params]
                torch._foreach_lerp_(mg, grads, 1.0 - group["decay"])
                denominator = torch._foreach_addcmul(rms, mg, mg, value=-1.0)
                torch._foreach_add_(denominator, group["epsilon"])
            else:
                denominator = torch._foreach_add(rms, group["epsilon"])
            torch._foreach_sqrt_(denominator)
            torch._foreach_mul_(mom, group["momentum"])
            torch._foreach_addcdiv_(mom, grads, denominator, value=group["lr"])
            torch._foreach_sub_(params, mom)
        return loss


def dopamine_dqn_loss(network: nn.Module, target_network: nn.Module,
                      batch: dc.TorchTransition, gamma: float,
                      huber_delta: float = 1.0) -> tuple[torch.Tensor, common.Metrics]:  # fmt: skip
    """Dopamine's DQN loss: the batch mean of Huber(r + gamma d max_a Q_target(s', a) - Q(s, a));
    ``gamma`` bootstraps (gamma^n for n-step batches)."""
    q_taken = dc.taken(network(batch.observation), batch.action)
    target = dc.dqn_target(network, target_network, batch, gamma, double_q=False)
    loss = dc.huber(target - q_taken, huber_delta).mean()
    return loss, {"critic/loss": loss, "critic/q": q_taken.mean(), "critic/target": target.mean()}


class DopamineDQNAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: DopamineDQNConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.batch_spec, self.num_steps = config.atari.batch_spec(), config.atari.num_steps
        self.pretrain_steps = 0
        self.network, self.target_network, self.optimizers, self.generators = dc.build(
            "dopamine_dqn", observation_spec, action_spec, config, seed, self.device, dc.QNetwork,
            # Dopamine's DQN learns with TF1's RMSProp, not the offline agents' Adam
            optimizer=lambda params: TFRMSProp(
                params, config.learning_rate, config.rmsprop_decay, config.rmsprop_momentum,
                config.rmsprop_epsilon, config.centered,
            ),
        )  # fmt: skip
        self.modules = {"network": self.network, "target_network": self.target_network}
        self.targets = {self.target_network: self.network}  # copied every target_update_period

    def update(self, batch: Transition) -> dict[str, float]:
        c = self.config
        loss, metrics = dopamine_dqn_loss(
            self.network, self.target_network, dc.to_torch(batch, self.device),
            self.batch_spec.bootstrap_gamma, c.atari.huber_delta,
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
        """Epsilon-greedy on Q: ``atari.eval_epsilon`` (Dopamine's 0.001) with ``greedy=True``,
        ``atari.explore_epsilon`` (its training epsilon, 0.01) with ``greedy=False``."""
        return dc.act(self.network, observation, self.config.atari, greedy, self.generators["act"])

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = DopamineDQNAgent
