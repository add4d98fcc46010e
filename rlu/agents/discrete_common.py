"""What the discrete (Atari) agents share: the paper's common settings as one frozen config,
the Nature CNN, and pure functions (Huber, TD targets, epsilon-greedy). No learning step lives
here: each agent file holds its own loss and update.

Paper appendix A.2 (table "Atari experiments hyper-parameters"): the Q-network is the Nature CNN
(channels 32, 64, 64; filters 8, 4, 3; strides 4, 2, 1; 512 hidden units), Adam with TF2's
default beta and epsilon (eps = 1e-7, not PyTorch's 1e-8), batch 256, discount 0.99, a hard
target update every 2500 updates, evaluation epsilon 0.4^8 and 2M learner steps. Rewards are
clipped to [-1, 1] for learning (Mnih et al. 2015; Dopamine's DQN, which generated the data);
evaluation scores the raw game score.

Observations are uint8 (B, H, W, C) frame stacks, newest frame last, or float (B, D) features
(bsuite), or a dict of one uint8 ``pixels`` frame and float vectors (DeepMind Lab's ``pixels``,
``last_action``, ``last_reward``): the vectors are concatenated, in key order, to the
convolutions' flat output before the hidden layer, as Acme's ``OAREmbedding`` (its R2D2
networks' input: torso features, the one-hot last action, tanh of the last reward) does; the
reward goes in as stored, not squashed. :func:`frames` turns them
into the networks' input once per batch: float (B, C, H, W) scaled by 1/255. The observations of
a learning step, whose convolutions run forward and backward, are laid out channels-last (oneDNN's
CPU forward + backward runs 12% faster on it at batch 32, 28% at batch 256, one thread); the next
observations, which only run forward (target and double-Q passes: within 3% on either layout),
keep the layout the store's views give (frame-major memory: NCHW, one cast away: 0.1 ms instead
of 0.6 ms at batch 32), and are converted once for both of their passes.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Generic, Literal, NamedTuple, TypeVar, overload

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents.common import TorchTransition
from rlu.files import (
    BATCH,
    FRACTION,
    STEPS,
    WIDTH,
    Checked,
    bounds,
)
from rlu.seeds import stream_seed
from rlu.types import ArraySpec, BatchSpec, DiscreteSpec, SpecError, Transition

EVAL_EPSILON = 0.4**8
"""The paper's evaluation epsilon (table in appendix A.2), taken literally: 0.4^8 ~ 6.6e-4."""

LEARNING_RATE_GRID = (3e-5, 5e-5, 1e-4)
"""The paper prints the learning-rate grid as [5e-5, 1e-4, 5e-5] (5e-5 twice) yet picks 3e-5
for DQN and BC, so the grid read here is {3e-5, 5e-5, 1e-4}: the values the paper names."""


@dataclass(frozen=True)
class AtariSettings(Checked):
    """The settings every discrete baseline shares (paper appendix A.2), composed into each
    agent's config as its ``atari`` field (override as ``atari.batch_size=32``)."""

    batch_size: int = field(default=256, metadata=BATCH)
    """Transitions per update."""
    gamma: float = field(default=0.99, metadata=FRACTION)
    """Discount factor of the TD target."""
    n_step: int = field(default=1, metadata=bounds(min=1, max=1000))
    """Steps summed into each transition's reward (the paper: 1-step targets)."""
    reward_clip: float = field(default=1.0, metadata=bounds(min=0.0, max=1e9))
    """Learning sees per-step rewards clipped to [-reward_clip, reward_clip] (the data keeps raw
    game scores; evaluation reports them)."""
    adam_eps: float = field(default=1e-7, metadata=FRACTION)
    """Adam epsilon: TF2's default, as the paper states."""
    eval_epsilon: float = field(default=EVAL_EPSILON, metadata=FRACTION)
    """Probability of a uniform action when acting greedily (the paper's evaluation epsilon)."""
    explore_epsilon: float = field(default=0.01, metadata=FRACTION)
    """Probability of a uniform action when acting with greedy=False (the online agent's)."""
    target_update_period: int = field(default=2500, metadata=STEPS)
    """Updates between hard copies of the online network into the target network."""
    huber_delta: float = field(default=1.0, metadata=bounds(min=1e-12, max=1e9))
    """Where the Huber loss of the TD error turns linear."""
    num_steps: int = field(default=2_000_000, metadata=STEPS)
    """Learner steps of a full run (the table's 2M): what ``rlu train`` runs without --steps."""
    channels: tuple[int, ...] = field(
        default=(32, 64, 64), metadata=bounds(min=1, max=4096, min_len=1, max_len=16)
    )
    """Nature CNN output channels per convolution."""
    kernel_sizes: tuple[int, ...] = field(
        default=(8, 4, 3), metadata=bounds(min=1, max=84, min_len=1, max_len=16)
    )
    """Nature CNN square filter sizes."""
    strides: tuple[int, ...] = field(
        default=(4, 2, 1), metadata=bounds(min=1, max=84, min_len=1, max_len=16)
    )
    """Nature CNN strides."""
    hidden_size: int = field(default=512, metadata=WIDTH)
    """Units of the fully connected layer after the convolutions."""

    def batch_spec(self) -> BatchSpec:
        return BatchSpec(
            self.batch_size, n_step=self.n_step, gamma=self.gamma, reward_clip=self.reward_clip
        )


SMALL = AtariSettings(
    batch_size=32,
    channels=(16, 32, 32),
    hidden_size=128,
    target_update_period=200,  # the paper's 2500 is 1/800 of its run; 200 is 1/100 of 20k
    num_steps=20_000,
)
"""The ``small`` presets' shared settings: a narrower Nature CNN, batch 32, 20k learner steps
(minutes on a 2-core CPU)."""

SMALL_FIELDS: dict[str, Any] = {"atari": SMALL, "learning_rate": 1e-4}
"""Every discrete ``small`` preset: the settings above and Adam 1e-4."""


# ----------------------------------------------------------------------------- specs and batches


Shape = tuple[int, ...] | Mapping[str, tuple[int, ...]]
"""An observation's shape as the networks take it: HWC frames, (D,) features, or a dict's
(``pixels`` HWC and the vectors' shapes)."""


def check_specs(name: str, observation_spec: Any, action_spec: Any) -> tuple[Shape, int]:
    """(observation shape HWC, (D,) or a dict's shapes, number of actions) or a SpecError naming
    the field and the fix."""
    if not isinstance(action_spec, DiscreteSpec):
        raise SpecError(
            f"{name}: action_spec is {action_spec!r}; the discrete agents need a DiscreteSpec "
            "(use the continuous agent of the same name for BoundedSpec actions)"
        )
    if isinstance(observation_spec, Mapping):
        return _dict_shapes(name, observation_spec), int(action_spec.num_values)
    if (
        isinstance(observation_spec, ArraySpec)
        and len(observation_spec.shape) == 1
        and np.dtype(observation_spec.dtype) == np.float32
    ):  # a float feature vector (bsuite): an MLP torso instead of the CNN
        return tuple(observation_spec.shape), int(action_spec.num_values)
    if not isinstance(observation_spec, ArraySpec) or len(observation_spec.shape) != 3:
        raise SpecError(
            f"{name}: observation_spec is {observation_spec!r}; the discrete agents take one "
            "uint8 frame stack ArraySpec((H, W, frames), 'uint8'), e.g. (84, 84, 4), or one "
            "float32 feature vector ArraySpec((D,), 'float32')"
        )
    if np.dtype(observation_spec.dtype) != np.uint8:
        raise SpecError(
            f"{name}: observation_spec.dtype is {observation_spec.dtype!r}; the Nature CNN scales "
            "uint8 frames by 1/255 itself, so pass the frames as uint8"
        )
    return tuple(observation_spec.shape), int(action_spec.num_values)


def _dict_shapes(name: str, spec: Mapping[str, Any]) -> Mapping[str, tuple[int, ...]]:
    """A dict observation the networks take: a uint8 HWC ``pixels`` frame and float32 vectors
    (shape () or (D,))."""
    pixels = spec.get("pixels")
    if not isinstance(pixels, ArraySpec) or len(pixels.shape) != 3 or pixels.dtype != "uint8":
        raise SpecError(
            f"{name}: a dict observation_spec needs 'pixels' ArraySpec((H, W, C), 'uint8') "
            f"(DeepMind Lab's), got {pixels!r} among keys {sorted(spec)}"
        )
    shapes = {"pixels": tuple(pixels.shape)}
    for k in sorted(set(spec) - {"pixels"}):
        v = spec[k]
        if not isinstance(v, ArraySpec) or len(v.shape) > 1 or v.dtype != "float32":
            raise SpecError(
                f"{name}: observation {k!r} is {v!r}; beside 'pixels' the discrete agents take "
                "float32 vectors ArraySpec(() or (D,), 'float32')"
            )
        shapes[k] = tuple(v.shape)
    return MappingProxyType(shapes)


@overload
def frames(x: Mapping[str, Any], field: str = ..., channels_last: bool = ...,
           device: torch.device | None = ...) -> dict[str, torch.Tensor]: ...  # fmt: skip
@overload
def frames(x: Any, field: str = ..., channels_last: bool = ...,
           device: torch.device | None = ...) -> torch.Tensor: ...  # fmt: skip
def frames(
    x: Any,
    field: str = "observation",
    channels_last: bool = False,
    device: torch.device | None = None,
) -> torch.Tensor | dict[str, torch.Tensor]:
    """uint8 (B, H, W, C) frame stacks (numpy, or a tensor the loop prepared) -> the networks'
    input on ``device``, float (B, C, H, W) / 255. The frames travel as uint8 and are scaled there.

    ``channels_last`` lays the result out channels-last (for a pass that runs backward too);
    otherwise it keeps the input's memory order (NCHW for the views' frame-major stacks).
    A dict observation gives a dict: ``pixels`` so converted, each other key a float (B, D)."""
    if isinstance(x, Mapping):
        if "pixels" not in x:
            raise SpecError(f"batch.{field} is a dict without 'pixels' (keys {sorted(x)})")
        out = {"pixels": _stacks(x["pixels"], f"{field}['pixels']", channels_last, device)}
        for k in sorted(set(x) - {"pixels"}):
            v = common.to_torch(x[k], device, "float32")
            out[k] = v.reshape(v.shape[0], -1)
        return out
    return _stacks(x, field, channels_last, device)


def _stacks(x: Any, field: str, channels_last: bool, device: torch.device | None) -> torch.Tensor:
    array = x if isinstance(x, torch.Tensor) else np.asarray(x)
    if array.dtype in (np.float32, torch.float32) and array.ndim == 2:  # (B, D) features
        return common.to_torch(array, device, "float32")
    if array.dtype not in (np.uint8, torch.uint8):
        raise SpecError(
            f"batch.{field} has dtype {array.dtype}; the discrete agents take uint8 frame stacks "
            "(B, H, W, frames), newest frame last, as the Atari views give them"
        )
    if array.ndim != 4:
        raise SpecError(
            f"batch.{field} has shape {tuple(array.shape)}; the discrete agents take a batch of "
            "frame stacks (B, H, W, frames): add the batch axis"
        )
    return scaled(common.to_torch(array, device), channels_last)


def scaled(stacks: torch.Tensor, channels_last: bool = False) -> torch.Tensor:
    """uint8 (B, H, W, C) tensor -> float (B, C, H, W) / 255 (see :func:`frames`)."""
    x = stacks.permute(0, 3, 1, 2)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    return x.float().mul_(1.0 / 255.0)


def to_torch(batch: Transition, device: torch.device | None = None) -> TorchTransition:
    """A batch as the losses take it, on ``device``: each observation converted once."""
    return TorchTransition(
        observation=frames(batch.observation, channels_last=True, device=device),
        action=common.to_torch(batch.action, device, "int64"),
        reward=common.to_torch(batch.reward, device, "float32"),
        discount=common.to_torch(batch.discount, device, "float32"),
        next_observation=frames(batch.next_observation, "next_observation", device=device),
    )


# ----------------------------------------------------------------------------- networks


class NatureTorso(nn.Module):
    """Mnih et al. (2015) convolutions, flat features out. Input: :func:`frames`' float
    (B, C, H, W) in [0, 1] (what the agents pass), or uint8 (B, H, W, C) stacks, which it
    converts itself the same way."""

    output_size: int  # the flat features' width

    def __init__(self, observation_shape: Shape, settings: AtariSettings) -> None:
        super().__init__()
        self.vectors: tuple[str, ...] = ()  # a dict's keys beside 'pixels', concatenated after
        if isinstance(observation_shape, Mapping):
            self.vectors = tuple(k for k in sorted(observation_shape) if k != "pixels")
            extra = sum(int(np.prod(observation_shape[k])) for k in self.vectors)
            self._convolutions(observation_shape["pixels"], settings)
            self.output_size += extra
            return
        if len(observation_shape) == 1:  # float features: one hidden layer instead of the convs
            self.convs = nn.Sequential(
                nn.Linear(observation_shape[0], settings.hidden_size), nn.ReLU()
            )
            self.output_size = settings.hidden_size
            return
        self._convolutions(observation_shape, settings)

    def _convolutions(self, observation_shape: tuple[int, ...], settings: AtariSettings) -> None:
        channels, kernels, strides = settings.channels, settings.kernel_sizes, settings.strides
        if not len(channels) == len(kernels) == len(strides):
            raise SpecError(
                f"atari settings: channels {channels}, kernel_sizes {kernels} and strides "
                f"{strides} must have the same length (one entry per convolution)"
            )
        height, width, in_channels = observation_shape
        layers: list[nn.Module] = []
        for out_channels, kernel, stride in zip(channels, kernels, strides, strict=True):
            layers += [nn.Conv2d(in_channels, out_channels, kernel, stride), nn.ReLU()]
            in_channels = out_channels
            height, width = (height - kernel) // stride + 1, (width - kernel) // stride + 1
            if height <= 0 or width <= 0:
                raise SpecError(
                    f"observation shape {observation_shape} is too small for kernels "
                    f"{kernels} with strides {strides}; use (84, 84, frames)"
                )
        self.convs = nn.Sequential(*layers)
        self.output_size = in_channels * height * width

    def forward(self, x: torch.Tensor | Mapping[str, torch.Tensor]) -> torch.Tensor:
        if isinstance(x, Mapping):  # pixels through the convolutions, the vectors beside them
            flat = self.forward(x["pixels"])
            return torch.cat([flat] + [x[k].reshape(flat.shape[0], -1) for k in self.vectors], 1)
        if x.dtype == torch.uint8:
            x = scaled(x)
        return self.convs(x).flatten(1)


class RecurrentCore(nn.Module):
    """The recurrent discrete agents' body (R2D2's, Kapturowski et al. 2019): the Nature torso
    -> ReLU(Linear ``hidden_size``) -> an LSTM of ``lstm_size``. ``forward(frames, batch,
    steps, state)`` takes :func:`frames` of (B*T, ...) observations (:func:`time_steps` flattens
    a window's) and the LSTM state ((1, B, H), (1, B, H)) or None (zeros); it returns the
    features (B, T, H) and the state after the last step."""

    def __init__(self, shape: Shape, settings: AtariSettings, lstm_size: int) -> None:
        super().__init__()
        self.torso = NatureTorso(shape, settings)
        self.embed = nn.Sequential(
            nn.Linear(self.torso.output_size, settings.hidden_size), nn.ReLU()
        )
        self.lstm = nn.LSTM(settings.hidden_size, lstm_size, batch_first=True)
        self.output_size = lstm_size

    def forward(
        self, frames: Any, batch: int, steps: int, state: common.LSTMState | None = None
    ) -> tuple[torch.Tensor, common.LSTMState]:
        x = self.embed(self.torso(frames)).reshape(batch, steps, -1)
        return self.lstm(x, state)


def time_steps(x: Any, start: int, stop: int) -> Any:
    """Steps [start, stop) of a window's (B, T, ...) arrays (a dict's each), flattened to
    (B * (stop - start), ...): what :func:`frames` and :class:`RecurrentCore` take."""
    if isinstance(x, Mapping):
        return {k: time_steps(v, start, stop) for k, v in x.items()}
    part = x[:, start:stop]
    return part.reshape(part.shape[0] * part.shape[1], *part.shape[2:])


def mlp_head(in_size: int, hidden_size: int, out_size: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(in_size, hidden_size), nn.ReLU(), nn.Linear(hidden_size, out_size)
    )


class QNetwork(nn.Module):
    """Nature CNN -> 512 -> num_heads x num_actions. Output (B, A), or (B, heads, A) if heads > 1
    (REM's multi-head network: one shared torso and hidden layer, as in Agarwal et al.)."""

    def __init__(
        self, shape: Shape, num_actions: int, settings: AtariSettings, num_heads: int = 1
    ) -> None:
        super().__init__()
        self.torso = NatureTorso(shape, settings)
        self.head = mlp_head(self.torso.output_size, settings.hidden_size, num_actions * num_heads)
        self.num_actions, self.num_heads = num_actions, num_heads

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        out = self.head(self.torso(frames))
        if self.num_heads == 1:
            return out
        return out.view(-1, self.num_heads, self.num_actions)


_Net = TypeVar("_Net", bound=nn.Module)
_Target = TypeVar("_Target", bound=nn.Module | None, covariant=True)


class DiscreteParts(NamedTuple, Generic[_Net, _Target]):
    """What :func:`build` makes for a discrete agent; the agent's file names where it keeps each."""

    network: _Net
    target_network: _Target
    optimizers: dict[str, torch.optim.Optimizer]
    generators: dict[str, torch.Generator]


_Optimizer = Callable[[list[nn.Parameter]], torch.optim.Optimizer]


@overload
def build(name: str, observation_spec: Any, action_spec: Any, config: Any, seed: int,
          device: torch.device, make: Callable[[Shape, int, AtariSettings], _Net],
          target: Literal[True] = True, optimizer: _Optimizer | None = None,
          ) -> DiscreteParts[_Net, _Net]: ...  # fmt: skip
@overload
def build(name: str, observation_spec: Any, action_spec: Any, config: Any, seed: int,
          device: torch.device, make: Callable[[Shape, int, AtariSettings], _Net],
          target: Literal[False], optimizer: _Optimizer | None = None,
          ) -> DiscreteParts[_Net, None]: ...  # fmt: skip
def build(
    name: str,
    observation_spec: Any,
    action_spec: Any,
    config: Any,
    seed: int,
    device: torch.device,
    make: Callable[[Shape, int, AtariSettings], _Net],
    target: bool = True,
    optimizer: _Optimizer | None = None,
) -> DiscreteParts[_Net, _Net | None]:
    """What every discrete agent owns, built the same way for each (specs checked first): the
    network ``make(frame shape, number of actions, config.atari)``, made on the CPU under the
    agent's initialisation seed and moved to ``device``; its frozen target copy (None with
    ``target=False``); ``{"network": optimizer(parameters)}``, by default Adam with TF2's
    epsilon at ``config.learning_rate``;
    ``{"learner": ..., "act": ...}`` generators on ``device`` (the loss's draws, acting). The
    network is built under ``seed`` itself, the generators' seeds are ``rlu.seeds.stream_seed``
    streams of it."""
    shape, num_actions = check_specs(name, observation_spec, action_spec)
    learner_seed, act_seed = stream_seed(seed, "learner"), stream_seed(seed, "act")
    with common.seeded(seed):
        network = make(shape, num_actions, config.atari).to(device)
    target_network = common.frozen_copy(network) if target else None
    params = list(network.parameters())
    opt: torch.optim.Optimizer
    if optimizer is None:
        opt = common.adam(params, config.learning_rate, config.atari.adam_eps)
    else:
        opt = optimizer(params)
    generators = {
        "learner": common.generator(learner_seed, device),
        "act": common.generator(act_seed, device),
    }
    return DiscreteParts(network, target_network, {"network": opt}, generators)


def dqn_target(
    network: nn.Module,
    target_network: nn.Module,
    batch: TorchTransition,
    gamma: float,
    double_q: bool = True,
) -> torch.Tensor:
    """The (double-)Q TD target of a batch, without gradients: :func:`double_q_target` with
    the online network's argmax, or :func:`q_learning_target` with the target's own max."""
    with torch.no_grad():
        q_next_target = target_network(batch.next_observation)
        if not double_q:
            return q_learning_target(batch.reward, batch.discount, gamma, q_next_target)
        q_next_online = network(batch.next_observation)
        return double_q_target(batch.reward, batch.discount, gamma, q_next_online, q_next_target)


# ----------------------------------------------------------------------------- pure maths


def huber(x: torch.Tensor, delta: float = 1.0) -> torch.Tensor:
    """Elementwise Huber: x^2/2 for |x| <= delta, delta (|x| - delta/2) beyond."""
    absolute = x.abs()
    return torch.where(absolute <= delta, 0.5 * x * x, delta * (absolute - 0.5 * delta))


def taken(values: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """values (B, A) at action (B,) -> (B,)."""
    return values.gather(-1, action[:, None]).squeeze(-1)


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


def epsilon_greedy(scores: torch.Tensor, epsilon: float, generator: torch.Generator) -> np.ndarray:
    """argmax of scores (B, A), replaced by a uniform action with probability epsilon. Both
    draws are always made, so the generator advances the same way whatever the outcome."""
    batch, num_actions = scores.shape
    explore = torch.rand(batch, generator=generator, device=scores.device) < epsilon
    uniform = torch.randint(num_actions, (batch,), generator=generator, device=scores.device)
    return torch.where(explore, uniform, scores.argmax(-1)).cpu().numpy().astype(np.int64)


def learn(
    optimizer: torch.optim.Optimizer,
    loss: torch.Tensor,
    step: int,
    settings: AtariSettings,
    targets: Mapping[_Net, nn.Module],
) -> int:
    """A discrete agent's gradient step (``common.learn``) with the hard copies into its target
    networks (``{target: source}``) every ``settings.target_update_period`` updates."""
    return common.learn(optimizer, loss, step, settings.target_update_period, targets)


def act(
    network: nn.Module,
    observation: Any,
    settings: AtariSettings,
    greedy: bool,
    generator: torch.Generator,
) -> np.ndarray:
    """Acting on a Q-network whose output is (B, A): :func:`epsilon_greedy` on Q(s, .) of the
    frame stacks ``observation`` (moved to the network's device), with :func:`epsilon`'s
    probability."""
    device = next(network.parameters()).device
    q = network(frames(observation, device=device))
    return epsilon_greedy(q, epsilon(settings, greedy), generator)


def epsilon(settings: AtariSettings, greedy: bool) -> float:
    """The acting epsilon: the paper's evaluation epsilon, or the online agent's exploration."""
    return settings.eval_epsilon if greedy else settings.explore_epsilon
