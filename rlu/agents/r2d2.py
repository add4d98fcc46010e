"""Recurrent Q-learning on stored sequences, R2D2-style (Kapturowski et al. 2019, "Recurrent
Experience Replay in Distributed Reinforcement Learning"), trained offline.

The agent that recorded the release's DeepMind Lab data was R2D2; the release's
``dmlab_r2d2.ipynb`` loads the sequences into one. This is its learner on fixed windows of the
stored episodes: a Nature CNN torso (``discrete_common.NatureTorso``; DeepMind Lab's
``last_action`` and ``last_reward`` concatenated to its output) -> a ``hidden_size`` layer -> an
LSTM -> a duelling head (Wang et al. 2016). Each window of ``burn_in + sequence_length`` steps
is unrolled from a zero state; the first ``burn_in`` steps only warm the LSTM state up (no
gradient through them), and the loss is over the last ``sequence_length``. Targets are n-step
double-Q with R2D2's invertible value rescaling h(x) = sign(x)(sqrt(|x| + 1) - 1) + eps x:
``h(sum_i gamma^i r_{t+i} + gamma^k d h^-1(Q_target(s_{t+k}, argmax_a Q(s_{t+k}, a))))``, with
k = n steps, fewer where the episode or the window ends first (a terminal step's discount 0 stops
the bootstrap; a time-limit end bootstraps from the last observation). The loss is half the
squared TD error, averaged over the real transitions of the learning steps; the target
network is a hard copy every ``atari.target_update_period`` updates.

Paper settings (Kapturowski et al. 2019, table 2): sequences of 80 after a burn-in of 40,
n = 5, discount 0.997, Adam 1e-4 with epsilon 1e-3, batch 64, target period 2500, LSTM 512,
value-rescaling epsilon 1e-3.

Deviations (offline, and what the data hold): windows are sampled uniformly (no prioritised
replay; R2D2's priorities need the actors); the state at a window's start is zero, not a stored
recurrent state (the release stores none; R2D2's "zero start state" with burn-in); windows
start anywhere in an episode and are padded past its end (``Sequence.mask``), not overlapping
fixed chunks, so a window that starts within ``burn_in`` steps of its episode's end teaches
nothing (``critic/transitions`` counts the transitions each update learnt from; it is 0 when
every episode is shorter than the burn-in); the Atari frame stacks carry no last action and
reward (DeepMind Lab's observations do); rewards are not clipped (the rescaling bounds the
targets, as in R2D2); ``atari.reward_clip`` and ``atari.huber_delta`` are unused.

Acting: the LSTM state of every row is kept between calls and reset where ``is_first`` (all
rows when the batch size changes); greedy is epsilon-greedy with ``atari.eval_epsilon``,
``greedy=False`` with ``atari.explore_epsilon``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents import discrete_common as dc
from rlu.agents import networks as nets
from rlu.files import FRACTION, LEARNING_RATE, Checked, bounds
from rlu.types import ActionSpec, BatchSpec, Observation, ObservationSpec, RluError, Sequence

PAPER_ATARI = dc.AtariSettings(
    batch_size=64, gamma=0.997, n_step=5, adam_eps=1e-3, target_update_period=2500
)
"""R2D2's settings among the shared ones (Kapturowski et al. 2019, table 2)."""


@dataclass(frozen=True)
class R2D2Config(Checked):
    atari: dc.AtariSettings = field(default_factory=lambda: PAPER_ATARI)
    """Network, batch (windows per update), discount, n-step, Adam epsilon, target period,
    epsilons and budget (R2D2's values: batch 64, gamma 0.997, n 5, Adam epsilon 1e-3)."""
    learning_rate: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam step size (R2D2's 1e-4)."""
    sequence_length: int = field(default=80, metadata=bounds(min=1, max=100_000))
    """Steps of a window the loss is over (R2D2's 80)."""
    burn_in: int = field(default=40, metadata=bounds(min=0, max=100_000))
    """Steps before them that only warm up the LSTM state (R2D2's 40)."""
    lstm_size: int = field(default=512, metadata=bounds(min=1, max=16384))
    """LSTM units (R2D2's 512)."""
    rescale_epsilon: float = field(default=1e-3, metadata=FRACTION)
    """The eps of the value rescaling h; 0 turns the rescaling off (plain n-step targets)."""


Config = R2D2Config

PRESETS: dict[str, R2D2Config] = {
    "paper": R2D2Config(),
    "small": R2D2Config(
        atari=dc.AtariSettings(
            batch_size=8,
            gamma=0.997,
            n_step=5,
            adam_eps=1e-3,
            target_update_period=200,
            channels=(16, 32, 32),
            hidden_size=128,
            num_steps=20_000,
        ),  # fmt: skip
        sequence_length=20,
        burn_in=10,
        lstm_size=128,
    ),
}

GRID: dict[str, list[Any]] = {"learning_rate": [3e-5, 1e-4, 3e-4]}


# ----------------------------------------------------------------------------- value rescaling


def rescale(x: torch.Tensor, eps: float) -> torch.Tensor:
    """h(x) = sign(x)(sqrt(|x| + 1) - 1) + eps x (identity when eps is 0: no rescaling)."""
    if eps == 0:
        return x
    return torch.sign(x) * (torch.sqrt(x.abs() + 1.0) - 1.0) + eps * x


def unrescale(x: torch.Tensor, eps: float) -> torch.Tensor:
    """h^-1: sign(x)(((sqrt(1 + 4 eps (|x| + 1 + eps)) - 1) / (2 eps))^2 - 1)."""
    if eps == 0:
        return x
    root = torch.sqrt(1.0 + 4.0 * eps * (x.abs() + 1.0 + eps))
    return torch.sign(x) * (((root - 1.0) / (2.0 * eps)) ** 2 - 1.0)


# ----------------------------------------------------------------------------- network


class R2D2Network(nn.Module):
    """``discrete_common.RecurrentCore`` (torso -> hidden layer -> LSTM) -> duelling Q.
    ``forward(frames, batch, steps, state)``: Q (B, T, A) and the LSTM state after the last
    step."""

    def __init__(self, shape: dc.Shape, num_actions: int, settings: dc.AtariSettings,
                 lstm_size: int) -> None:  # fmt: skip
        super().__init__()
        self.core = dc.RecurrentCore(shape, settings, lstm_size)
        self.value = nn.Linear(lstm_size, 1)
        self.advantage = nn.Linear(lstm_size, num_actions)

    def forward(
        self, frames: Any, batch: int, steps: int, state: common.LSTMState | None = None
    ) -> tuple[torch.Tensor, common.LSTMState]:
        out, state = self.core(frames, batch, steps, state)
        adv = self.advantage(out)
        return self.value(out) + adv - adv.mean(-1, keepdim=True), state


# ----------------------------------------------------------------------------- the loss


def n_step_targets(reward: torch.Tensor, discount: torch.Tensor, valid: torch.Tensor,
                   end: torch.Tensor, q_boot: torch.Tensor, gamma: float,
                   n: int) -> torch.Tensor:  # fmt: skip
    """The n-step target of each step t of (B, T), before rescaling: sum_{i<k} gamma^i
    (prod_{j<i} d_{t+j}) r_{t+i} + gamma^k (prod_{j<k} d_{t+j}) q_boot[t + k], with
    k = min(n, end - t) (``end`` (B,): the index of each row's last real step) and ``q_boot``
    (B, T) the bootstrap value of each step as a next state (already h^-1'd); 0 where ``valid``
    (the steps that are real transitions, a real step after them) is False."""
    b, t = reward.shape
    steps = torch.arange(t, device=reward.device).expand(b, t)
    k = (end[:, None] - steps).clamp(min=0, max=n)
    ret = torch.zeros_like(reward)
    scale = torch.ones_like(reward)  # gamma^i times the discounts before step t + i
    for i in range(n):
        idx = (steps + i).clamp(max=t - 1)
        live = (i < k).float()
        ret = ret + live * scale * reward.gather(1, idx)
        scale = torch.where(i < k, scale * gamma * discount.gather(1, idx), scale)
    boot = q_boot.gather(1, (steps + k).clamp(max=t - 1))
    return torch.where(valid, ret + scale * boot, torch.zeros_like(ret))


def r2d2_loss(network: R2D2Network, target_network: R2D2Network, batch: Sequence,
              config: R2D2Config,
              device: torch.device) -> tuple[torch.Tensor, common.Metrics]:  # fmt: skip
    """Half the squared TD error (in rescaled units) over the real transitions of the learning
    steps (module docstring)."""
    s, burn = config.atari, config.burn_in
    action = common.to_torch(batch.action, device, "int64")
    length = action.shape[1]
    if length <= burn:
        raise RluError(f"r2d2: windows of {length} steps leave none after burn_in={burn}")
    b = action.shape[0]
    mask = common.to_torch(batch.mask, device).bool()
    is_last = common.to_torch(batch.is_last, device).bool()
    reward = common.to_torch(batch.reward, device, "float32") * mask
    discount = common.to_torch(batch.discount, device, "float32")
    steps = torch.arange(length, device=device).expand(b, length)
    end = torch.where(mask, steps, torch.full_like(steps, -1)).max(1).values  # last real step
    valid = mask & ~is_last & (steps < end[:, None])
    obs = batch.observation
    learn = length - burn
    with torch.no_grad():
        state = target_state = None
        if burn:
            warm = dc.frames(dc.time_steps(obs, 0, burn), device=device)
            _, state = network(warm, b, burn, None)
            _, target_state = target_network(warm, b, burn, None)
        later = dc.frames(dc.time_steps(obs, burn, length), device=device)
        q_target, _ = target_network(later, b, learn, target_state)
    q, _ = network(dc.frames(dc.time_steps(obs, burn, length), channels_last=True, device=device),
                   b, learn, state)  # fmt: skip
    with torch.no_grad():
        best = q.argmax(-1, keepdim=True)  # double Q: the online network picks
        q_boot = unrescale(q_target.gather(-1, best).squeeze(-1), config.rescale_epsilon)
        sl = slice(burn, length)
        target = n_step_targets(reward[:, sl], discount[:, sl], valid[:, sl], end - burn,
                                q_boot, s.gamma, s.n_step)  # fmt: skip
        target = rescale(target, config.rescale_epsilon)
    q_taken = q.gather(-1, action[:, sl, None]).squeeze(-1)
    weight = valid[:, sl].float()
    count = weight.sum().clamp(min=1.0)
    loss = 0.5 * ((target - q_taken) ** 2 * weight).sum() / count
    mean_q = (q_taken.detach() * weight).sum() / count
    return loss, {"critic/loss": loss, "critic/q": mean_q,
                  "critic/target": (target * weight).sum() / count,
                  "critic/transitions": weight.sum()}  # fmt: skip


# ----------------------------------------------------------------------------- the agent


class R2D2Agent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: R2D2Config,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        s = config.atari
        self.batch_spec = BatchSpec(
            s.batch_size, kind="sequence", sequence_length=config.burn_in + config.sequence_length,
            gamma=s.gamma,
        )  # fmt: skip
        self.num_steps, self.pretrain_steps = s.num_steps, 0

        def make(shape: dc.Shape, num_actions: int, settings: dc.AtariSettings) -> R2D2Network:
            return R2D2Network(shape, num_actions, settings, config.lstm_size)

        self.network, self.target_network, self.optimizers, self.generators = dc.build(
            "r2d2", observation_spec, action_spec, config, seed, self.device, make
        )
        self.modules = {"network": self.network, "target_network": self.target_network}
        self.targets = {self.target_network: self.network}
        self._state: common.LSTMState | None = None  # acting's LSTM state

    def update(self, batch: Sequence) -> dict[str, float]:
        loss, metrics = r2d2_loss(self.network, self.target_network, batch, self.config,
                                  self.device)  # fmt: skip
        self.step = dc.learn(self.optimizers["network"], loss, self.step, self.config.atari,
                             self.targets)  # fmt: skip
        return common.metrics_to_floats(metrics)

    @torch.inference_mode()
    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """One step of every row's LSTM (reset where ``is_first``), epsilon-greedy on its Q."""
        x = dc.frames(observation, device=self.device)
        n = (x["pixels"] if isinstance(x, dict) else x).shape[0]
        state = nets.carried_state(self._state, is_first, x)
        q, self._state = self.network(x, n, 1, state)
        eps = dc.epsilon(self.config.atari, greedy)
        return dc.epsilon_greedy(q[:, 0], eps, self.generators["act"])

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)
        self._state = None


Agent = R2D2Agent
