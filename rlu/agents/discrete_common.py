"""Shared pure helpers of the discrete (Atari) baselines: Nature CNN, targets, losses, acting.

Paper appendix A.2 (table "Atari experiments hyper-parameters"): the Q-network is the Nature CNN
(channels 32, 64, 64; filters 8, 4, 3; strides 4, 2, 1; 512 hidden units), Adam with TF2's
default beta and epsilon (eps = 1e-7, not PyTorch's 1e-8), batch 256, discount 0.99, a hard
target update every 2500 updates, evaluation epsilon 0.4^8 and 2M learner steps.

The agents that differ only in their loss (BC, DQN, REM, IQN, BCQ) share code the Acme way: one
:class:`SGDLearner` (network, target copy, Adam, step counter, RNG) composed with a frozen loss
dataclass (``DoubleQLoss``, ``REMLoss``, ``QuantileLoss``, ``BCQLoss``, ``BCLoss``), each a
callable ``loss(network, target_network, batch, generator) -> (loss, metrics)``. There is no
parent agent class.

Observations are uint8 (B, H, W, C) frame stacks, newest frame last; the networks scale by 1/255
themselves. The frames enter the first convolution as a channels-last NCHW tensor, the layout
oneDNN's CPU convolutions prefer (a free permute for HWC-contiguous frames, one uint8 copy for
the frame-major stacks the store's views build).

Determinism: every random draw goes through the agent's own generators (initialisation under a
forked global RNG, one ``torch.Generator`` for the learner's draws, one for acting), all held in
``state_dict``. On the CPU the same seed gives bit-identical numbers for the same torch thread
count; a different thread count may change the last bits of a float reduction.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from rlu.types import ArraySpec, DiscreteSpec, SpecError, Transition

EVAL_EPSILON = 0.4**8
"""The paper's evaluation epsilon (table in appendix A.2), taken literally: 0.4^8 ~ 6.6e-4."""

LEARNING_RATE_GRID = (3e-5, 5e-5, 1e-4)

# The ``small`` presets of every discrete agent: a narrower Nature CNN, batch 32 and 20k steps
# (minutes on a 2-core CPU); agents with a target network add SMALL_TARGET_UPDATE_PERIOD.
SMALL_SCALE: dict[str, Any] = dict(
    learning_rate=1e-4, batch_size=32, num_steps=20_000, channels=(16, 32, 32), hidden_size=128
)
SMALL_TARGET_UPDATE_PERIOD = 200
"""The paper prints the grid as [5e-5, 1e-4, 5e-5] (5e-5 twice) yet picks 3e-5 for DQN and BC,
so the grid read here is {3e-5, 5e-5, 1e-4}: the values the paper names."""


# ----------------------------------------------------------------------------- specs and batches


def check_specs(name: str, observation_spec: Any, action_spec: Any) -> tuple[tuple[int, ...], int]:
    """(observation shape HWC, number of actions) or a SpecError naming the field and the fix."""
    if not isinstance(action_spec, DiscreteSpec):
        raise SpecError(
            f"{name}: action_spec is {action_spec!r}; the discrete agents need a DiscreteSpec "
            "(use the continuous agent of the same name for BoundedSpec actions)"
        )
    if not isinstance(observation_spec, ArraySpec) or len(observation_spec.shape) != 3:
        raise SpecError(
            f"{name}: observation_spec is {observation_spec!r}; the discrete agents take one "
            "uint8 frame stack ArraySpec((H, W, frames), 'uint8'), e.g. (84, 84, 4)"
        )
    if np.dtype(observation_spec.dtype) != np.uint8:
        raise SpecError(
            f"{name}: observation_spec.dtype is {observation_spec.dtype!r}; the Nature CNN scales "
            "uint8 frames by 1/255 itself, so pass the frames as uint8"
        )
    return tuple(observation_spec.shape), int(action_spec.num_values)


class TorchTransition(NamedTuple):
    """A :class:`rlu.types.Transition` as CPU tensors (observations stay uint8)."""

    observation: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    discount: torch.Tensor
    next_observation: torch.Tensor
    next_action: torch.Tensor


def frames_to_tensor(frames: Any, field: str = "observation") -> torch.Tensor:
    array = np.asarray(frames)
    if array.dtype != np.uint8:
        raise SpecError(
            f"batch.{field} has dtype {array.dtype}; the discrete agents take uint8 frame stacks "
            "(B, H, W, frames), newest frame last, as the Atari views give them"
        )
    if not array.flags.writeable:  # the store hands out read-only views; torch wants writable
        array = array.copy()
    return torch.from_numpy(array)


def to_torch(batch: Transition) -> TorchTransition:
    return TorchTransition(
        observation=frames_to_tensor(batch.observation),
        action=torch.as_tensor(np.asarray(batch.action, np.int64)),
        reward=torch.as_tensor(np.asarray(batch.reward, np.float32)),
        discount=torch.as_tensor(np.asarray(batch.discount, np.float32)),
        next_observation=frames_to_tensor(batch.next_observation, "next_observation"),
        next_action=torch.as_tensor(np.asarray(batch.next_action, np.int64)),
    )


def seeds(seed: int) -> tuple[int, int, int]:
    """Independent seeds for (initialisation, learner sampling, acting) from one agent seed."""
    a, b, c = np.random.SeedSequence(seed).generate_state(3)
    return int(a), int(b), int(c)


def build_seeded(seed: int, build: Callable[[], nn.Module]) -> nn.Module:
    """``build()`` under a private copy of torch's global RNG: the same seed gives the same
    weights and the caller's global RNG is left as it was."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return build()


# ----------------------------------------------------------------------------- networks


class NatureTorso(nn.Module):
    """Mnih et al. (2015) convolutions; uint8 (B, H, W, C) in, flat float features out."""

    def __init__(
        self,
        observation_shape: tuple[int, ...],
        channels: tuple[int, ...],
        kernel_sizes: tuple[int, ...],
        strides: tuple[int, ...],
    ) -> None:
        super().__init__()
        if not len(channels) == len(kernel_sizes) == len(strides):
            raise ValueError(
                f"config: channels {channels}, kernel_sizes {kernel_sizes} and strides {strides} "
                "must have the same length (one entry per convolution)"
            )
        height, width, in_channels = observation_shape
        layers: list[nn.Module] = []
        for out_channels, kernel, stride in zip(channels, kernel_sizes, strides, strict=True):
            layers += [nn.Conv2d(in_channels, out_channels, kernel, stride), nn.ReLU()]
            in_channels = out_channels
            height, width = (height - kernel) // stride + 1, (width - kernel) // stride + 1
            if height <= 0 or width <= 0:
                raise SpecError(
                    f"observation shape {observation_shape} is too small for kernels "
                    f"{kernel_sizes} with strides {strides}; use (84, 84, frames)"
                )
        self.convs = nn.Sequential(*layers)
        self.output_size = in_channels * height * width

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        # NCHW view of HWC frames, made channels-last in uint8 (cheap; a no-op for HWC-contiguous
        # frames): oneDNN's convolutions run ~25% faster on it than on the frame-major stacks
        # the views build.
        x = frames.permute(0, 3, 1, 2).contiguous(memory_format=torch.channels_last)
        x = x.float().mul_(1.0 / 255.0)
        return self.convs(x).flatten(1)


def mlp_head(in_size: int, hidden_size: int, out_size: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(in_size, hidden_size), nn.ReLU(), nn.Linear(hidden_size, out_size)
    )


class QNetwork(nn.Module):
    """Nature CNN -> 512 -> num_heads x num_actions. Output (B, A), or (B, heads, A) if heads > 1
    (REM's multi-head network: one shared torso and hidden layer, as in Agarwal et al.)."""

    def __init__(
        self, torso: NatureTorso, hidden_size: int, num_actions: int, num_heads: int = 1
    ) -> None:
        super().__init__()
        self.torso = torso
        self.head = mlp_head(torso.output_size, hidden_size, num_actions * num_heads)
        self.num_actions, self.num_heads = num_actions, num_heads

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        out = self.head(self.torso(frames))
        if self.num_heads == 1:
            return out
        return out.view(-1, self.num_heads, self.num_actions)


class QAndPolicyNetwork(nn.Module):
    """Discrete BCQ (Fujimoto et al. 2019): shared torso, a Q head and an imitation logits head."""

    def __init__(self, torso: NatureTorso, hidden_size: int, num_actions: int) -> None:
        super().__init__()
        self.torso = torso
        self.q_head = mlp_head(torso.output_size, hidden_size, num_actions)
        self.policy_head = mlp_head(torso.output_size, hidden_size, num_actions)

    def forward(self, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        features = self.torso(frames)
        return self.q_head(features), self.policy_head(features)


class ImplicitQuantileNetwork(nn.Module):
    """IQN (Dabney et al. 2018): Z(s, tau) = f(psi(s) * phi(tau)); output (B, N, A)."""

    def __init__(
        self, torso: NatureTorso, hidden_size: int, num_actions: int, embedding_size: int
    ) -> None:
        super().__init__()
        self.torso = torso
        self.embedding_size = embedding_size
        self.tau_layer = nn.Linear(embedding_size, torso.output_size)
        self.head = mlp_head(torso.output_size, hidden_size, num_actions)

    def forward(self, frames: torch.Tensor, taus: torch.Tensor) -> torch.Tensor:
        features = self.torso(frames)  # (B, D)
        phi = F.relu(self.tau_layer(cosine_tau_embedding(taus, self.embedding_size)))  # (B, N, D)
        return self.head(features[:, None, :] * phi)


# ----------------------------------------------------------------------------- pure maths


def huber(x: torch.Tensor, delta: float = 1.0) -> torch.Tensor:
    """Elementwise Huber: x^2/2 for |x| <= delta, delta (|x| - delta/2) beyond."""
    absolute = x.abs()
    return torch.where(absolute <= delta, 0.5 * x * x, delta * (absolute - 0.5 * delta))


def double_q_target(
    reward: torch.Tensor,
    discount: torch.Tensor,
    gamma: float,
    q_next_online: torch.Tensor,
    q_next_target: torch.Tensor,
) -> torch.Tensor:
    """van Hasselt et al. (2016): r + gamma d Q_target(s', argmax_a Q_online(s', a))."""
    best = q_next_online.argmax(-1, keepdim=True)
    return reward + gamma * discount * q_next_target.gather(-1, best).squeeze(-1)


def q_learning_target(
    reward: torch.Tensor, discount: torch.Tensor, gamma: float, q_next_target: torch.Tensor
) -> torch.Tensor:
    """Mnih et al. (2015): r + gamma d max_a Q_target(s', a)."""
    return reward + gamma * discount * q_next_target.max(-1).values


def random_convex_weights(num_heads: int, generator: torch.Generator) -> torch.Tensor:
    """REM's alpha: uniform draws normalised to sum to one (Agarwal et al. 2020, one per batch)."""
    weights = torch.rand(num_heads, generator=generator)
    return weights / weights.sum()


def cosine_tau_embedding(taus: torch.Tensor, embedding_size: int) -> torch.Tensor:
    """IQN eq. (4): cos(pi i tau) for i = 0 .. n-1; (..., N) -> (..., N, n).

    Dopamine uses i = 1 .. n; we follow the paper (i = 0 is a constant feature, a bias)."""
    i = torch.arange(embedding_size, dtype=taus.dtype)
    return torch.cos(math.pi * taus[..., None] * i)


def quantile_huber_loss(
    quantiles: torch.Tensor, taus: torch.Tensor, targets: torch.Tensor, kappa: float = 1.0
) -> torch.Tensor:
    """IQN eq. (3) per batch element: sum_i mean_j rho^kappa_{tau_i}(T_j - Z_i).

    quantiles (B, N) at fractions taus (B, N); targets (B, N') -> (B,). With kappa = 0 the Huber
    part becomes |u| (plain quantile regression)."""
    u = targets[:, None, :] - quantiles[:, :, None]  # (B, N, N')
    weight = (taus[:, :, None] - (u.detach() < 0).float()).abs()
    if kappa > 0:
        elementwise = weight * huber(u, kappa) / kappa
    else:
        elementwise = weight * u.abs()
    return elementwise.mean(2).sum(1)


def bcq_action_mask(logits: torch.Tensor, threshold: float) -> torch.Tensor:
    """Discrete BCQ's allowed actions: pi(a|s) / max_a' pi(a'|s) >= threshold.

    Threshold 0 allows every action (DQN), threshold 1 only the behaviour model's argmax.
    Fujimoto's code uses a strict '>', which at the paper's grid value 1.0 would mask every
    action; '>=' keeps 1.0 meaningful. Computed in log space, so no probability underflows."""
    if threshold <= 0:
        return torch.ones_like(logits, dtype=torch.bool)
    log_ratio = logits - logits.max(-1, keepdim=True).values  # log pi(a) - log max pi
    return log_ratio >= math.log(threshold)


def masked_argmax(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return values.masked_fill(~mask, float("-inf")).argmax(-1)


def epsilon_greedy(scores: torch.Tensor, epsilon: float, generator: torch.Generator) -> np.ndarray:
    """argmax of scores (B, A), replaced by a uniform action with probability epsilon. Both
    draws are always made, so the generator advances the same way whatever the outcome."""
    batch, num_actions = scores.shape
    explore = torch.rand(batch, generator=generator) < epsilon
    uniform = torch.randint(num_actions, (batch,), generator=generator)
    return torch.where(explore, uniform, scores.argmax(-1)).numpy().astype(np.int64)


# ----------------------------------------------------------------------------- losses (Acme style)

Metrics = dict[str, torch.Tensor]


def _gather(values: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """values (B, A) at action (B,) -> (B,)."""
    return values.gather(-1, action[:, None]).squeeze(-1)


def _gather_quantiles(quantiles: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """quantiles (B, N, A) at action (B,) -> (B, N)."""
    index = action[:, None, None].expand(-1, quantiles.shape[1], 1)
    return quantiles.gather(-1, index).squeeze(-1)


@dataclass(frozen=True)
class DoubleQLoss:
    """DQN with Huber loss; double-Q target when ``double_q`` (the paper's offline DQN)."""

    discount: float
    huber_delta: float = 1.0
    double_q: bool = True

    def __call__(self, network, target_network, batch: TorchTransition, generator):
        q = network(batch.observation)
        q_taken = _gather(q, batch.action)
        with torch.no_grad():
            q_next_target = target_network(batch.next_observation)
            if self.double_q:
                q_next_online = network(batch.next_observation)
                target = double_q_target(
                    batch.reward, batch.discount, self.discount, q_next_online, q_next_target
                )
            else:
                target = q_learning_target(
                    batch.reward, batch.discount, self.discount, q_next_target
                )
        loss = huber(target - q_taken, self.huber_delta).mean()
        return loss, {
            "critic/loss": loss,
            "critic/q": q_taken.mean(),
            "critic/target": target.mean(),
        }


@dataclass(frozen=True)
class REMLoss:
    """Random Ensemble Mixture: Huber loss on one random convex combination of the heads per
    batch, with the Q-learning (max) target of the same combination of the target heads."""

    discount: float
    num_heads: int
    huber_delta: float = 1.0

    def __call__(self, network, target_network, batch: TorchTransition, generator):
        alpha = random_convex_weights(self.num_heads, generator)
        q = torch.einsum("bka,k->ba", network(batch.observation), alpha)
        q_taken = _gather(q, batch.action)
        with torch.no_grad():
            q_next = torch.einsum("bka,k->ba", target_network(batch.next_observation), alpha)
            target = q_learning_target(batch.reward, batch.discount, self.discount, q_next)
        loss = huber(target - q_taken, self.huber_delta).mean()
        return loss, {
            "critic/loss": loss,
            "critic/q": q_taken.mean(),
            "critic/target": target.mean(),
        }


@dataclass(frozen=True)
class QuantileLoss:
    """IQN: quantile Huber loss between N online quantiles and N' target quantiles. The next
    action is the argmax of the mean of the target quantiles (Acme's IQN learner); with
    ``double_q`` it is the online network's on its own draw of N' fractions."""

    discount: float
    num_tau_samples: int = 16
    num_tau_prime_samples: int = 16
    kappa: float = 1.0
    double_q: bool = False

    def __call__(self, network, target_network, batch: TorchTransition, generator):
        size = batch.action.shape[0]
        taus = torch.rand(size, self.num_tau_samples, generator=generator)
        quantiles = _gather_quantiles(network(batch.observation, taus), batch.action)
        with torch.no_grad():
            taus_next = torch.rand(size, self.num_tau_prime_samples, generator=generator)
            next_quantiles = target_network(batch.next_observation, taus_next)  # (B, N', A)
            if self.double_q:
                selector = network(batch.next_observation, taus_next).mean(1)
            else:
                selector = next_quantiles.mean(1)
            next_taken = _gather_quantiles(next_quantiles, selector.argmax(-1))
            targets = batch.reward[:, None] + self.discount * batch.discount[:, None] * next_taken
        loss = quantile_huber_loss(quantiles, taus, targets, self.kappa).mean()
        return loss, {
            "critic/loss": loss,
            "critic/q": quantiles.mean(),
            "critic/target": targets.mean(),
        }


@dataclass(frozen=True)
class BCQLoss:
    """Discrete BCQ (Fujimoto et al. 2019): double-Q target restricted to the actions whose
    behaviour probability ratio passes ``threshold``, plus the imitation head's cross-entropy
    and a 1e-2 penalty on its logits (as in the authors' code)."""

    discount: float
    threshold: float = 0.5
    huber_delta: float = 1.0
    logit_penalty: float = 1e-2

    def __call__(self, network, target_network, batch: TorchTransition, generator):
        q, logits = network(batch.observation)
        q_taken = _gather(q, batch.action)
        with torch.no_grad():
            q_next_online, logits_next = network(batch.next_observation)
            q_next_target, _ = target_network(batch.next_observation)
            best = masked_argmax(q_next_online, bcq_action_mask(logits_next, self.threshold))
            target = batch.reward + self.discount * batch.discount * _gather(q_next_target, best)
        q_loss = huber(target - q_taken, self.huber_delta).mean()
        bc_loss = F.cross_entropy(logits, batch.action)
        loss = q_loss + bc_loss + self.logit_penalty * logits.pow(2).mean()
        return loss, {
            "critic/loss": q_loss,
            "critic/q": q_taken.mean(),
            "critic/target": target.mean(),
            "actor/bc_loss": bc_loss,
        }


@dataclass(frozen=True)
class BCLoss:
    """Behaviour cloning: cross-entropy of the policy logits on the logged actions."""

    def __call__(self, network, target_network, batch: TorchTransition, generator):
        logits = network(batch.observation)
        loss = F.cross_entropy(logits, batch.action)
        accuracy = (logits.argmax(-1) == batch.action).float().mean()
        return loss, {"actor/bc_loss": loss, "actor/accuracy": accuracy}


# ----------------------------------------------------------------------------- the learner


class SGDLearner:
    """Acme's SGD learner: a network, its target copy, Adam and a loss; one gradient step per
    :meth:`step`, a hard target update every ``target_update_period`` steps (0: no target)."""

    def __init__(
        self,
        network: nn.Module,
        loss: Callable[..., tuple[torch.Tensor, Metrics]],
        learning_rate: float,
        adam_eps: float,
        target_update_period: int,
        seed: int,
    ) -> None:
        self.network = network
        self.loss = loss
        self.target_update_period = target_update_period
        self.target_network = None
        if target_update_period > 0:
            self.target_network = copy.deepcopy(network).requires_grad_(False)
        self.optimizer = torch.optim.Adam(network.parameters(), lr=learning_rate, eps=adam_eps)
        self.generator = torch.Generator().manual_seed(seed)
        self.steps = 0

    @classmethod
    def from_config(cls, network: nn.Module, loss: Callable[..., Any], config: Any, seed: int):
        """The learner an agent config describes (``target_update_period`` absent: no target)."""
        period = getattr(config, "target_update_period", 0)
        return cls(network, loss, config.learning_rate, config.adam_eps, period, seed)

    def step(self, batch: TorchTransition) -> dict[str, float]:
        loss, metrics = self.loss(self.network, self.target_network, batch, self.generator)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.steps += 1
        if self.target_network is not None and self.steps % self.target_update_period == 0:
            self.target_network.load_state_dict(self.network.state_dict())
        values = torch.stack([v.detach().float() for v in metrics.values()]).tolist()
        return dict(zip(metrics, values, strict=True))

    def state_dict(self) -> dict[str, Any]:
        state = {
            "network": self.network.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "steps": self.steps,
            "generator": self.generator.get_state(),
        }
        if self.target_network is not None:
            state["target_network"] = self.target_network.state_dict()
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.network.load_state_dict(state["network"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.steps = int(state["steps"])
        self.generator.set_state(state["generator"])
        if self.target_network is not None:
            self.target_network.load_state_dict(state["target_network"])


def agent_state(learner: SGDLearner, act_generator: torch.Generator) -> dict[str, Any]:
    return {"learner": learner.state_dict(), "act_generator": act_generator.get_state()}


def load_agent_state(
    learner: SGDLearner, act_generator: torch.Generator, state: Mapping[str, Any]
) -> None:
    learner.load_state_dict(state["learner"])
    act_generator.set_state(state["act_generator"])
