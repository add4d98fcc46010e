"""Shared network pieces of the continuous agents (paper appendix A.1).

- ``Encoder``: dict observation -> one feature vector. Float entries are flattened and
  concatenated in **sorted-key order** (so the layout does not depend on the order a spec or a
  file happened to list its keys); every uint8 rank-3 entry (a camera image, HWC) goes through
  its own ``ResNetTorso`` and the embeddings are concatenated after the features.
- ``ResNetTorso``: IMPALA-style residual stacks, blocks (2, 2, 2), channels (16, 32, 32),
  3x3 convolutions, stride-2 downsampling, then a linear layer (512 units for D4PG with ReLU,
  64 for ABM / BC with instance norm + ELU: appendix table 5).
- ``ResidualMLP``: the paper's 8 x 1024 MLP with residual connections and a normalisation after
  every two layers. The paper's "instance normalisation" of a feature vector normalises each
  example over its features, which is ``nn.LayerNorm``; that is what we use.
- ``Torso``: Encoder -> ResidualMLP -> optional 2-layer LSTM (the sequence tasks).
- ``MixtureHead``: 5-component diagonal Gaussian mixture policy (evaluation variance 1e-4);
  ``GaussianHead`` the single Gaussian of RABM; ``CategoricalHead`` the distributional critic.
- ``TwinCritic``: two Q MLPs on one encoder (IQL, CQL, BRAC, TD3+BC; ReBRAC's with a
  LayerNorm after every hidden ReLU); ``TanhGaussianPolicy``: the
  tanh-squashed Gaussian policy of SAC-style agents (CQL, BRAC), with
  ``sample_tanh_gaussian`` for its reparameterised samples and their log densities;
  ``DeterministicPolicy``: TD3's tanh actor (TD3+BC, ReBRAC).
- ``ObservationNormaliser``: a dataset's observation mean and std (``rlu.types.DataStatistics``)
  as buffers, applied per entry (TD3+BC's state normalisation).
- ``variance_scaling_``: TF/Keras' ``VarianceScaling`` initializer (what Acme's networks name),
  ``truncated_normal_``: TF's ``truncated_normal`` (Sonnet's default ``snt.Linear`` weights).

Network pieces only: seeding, tensors, optimisers and the checkpoint format are in
``rlu.agents.common``, shared with the discrete agents.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from rlu.agents.common import LSTMState, TensorObservation
from rlu.agents.losses import tanh_gaussian_log_prob
from rlu.types import ActionSpec, ArraySpec, BoundedSpec, ObservationSpec, RluError, SpecError


def is_image(spec: ArraySpec) -> bool:
    return np.dtype(spec.dtype) == np.uint8 and len(spec.shape) == 3


def _as_dict(spec: ObservationSpec) -> dict[str, ArraySpec]:
    if isinstance(spec, ArraySpec):
        return {"": spec}
    return dict(spec)


class ResNetTorso(nn.Module):
    """IMPALA-style ResNet for HWC uint8 images (appendix table 5)."""

    def __init__(
        self,
        image_shape: tuple[int, ...],
        channels: tuple[int, ...] = (16, 32, 32),
        blocks: tuple[int, ...] = (2, 2, 2),
        hidden: int = 64,
        norm_elu: bool = True,
    ) -> None:
        super().__init__()
        h, w, c = image_shape
        act: type[nn.Module] = nn.ELU if norm_elu else nn.ReLU
        layers: list[nn.Module] = []
        for ch, nb in zip(channels, blocks, strict=True):
            layers += [nn.Conv2d(c, ch, 3, padding=1), nn.MaxPool2d(3, stride=2, padding=1)]
            layers += [_ResBlock(ch, act) for _ in range(nb)]
            c = ch
            h, w = (h + 1) // 2, (w + 1) // 2
        layers += [act(), nn.Flatten(), nn.Linear(c * h * w, hidden)]
        if norm_elu:
            layers.append(nn.LayerNorm(hidden))
        layers.append(act())
        self.net = nn.Sequential(*layers)
        self.output_dim = hidden

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = image.permute(0, 3, 1, 2).float() * (1.0 / 255.0)
        return self.net(x)


class _ResBlock(nn.Module):
    def __init__(self, channels: int, act: type[nn.Module]) -> None:
        super().__init__()
        self.net = nn.Sequential(
            act(), nn.Conv2d(channels, channels, 3, padding=1),
            act(), nn.Conv2d(channels, channels, 3, padding=1),
        )  # fmt: skip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.net(x)


def _flat_float(x: torch.Tensor, batch_dims: int, lead: torch.Size) -> torch.Tensor:
    """``x.reshape(*lead, -1).float()``, skipping the two ops where they change nothing (most
    state features arrive flat and float32: the update calls the encoder several times)."""
    if x.dim() != batch_dims + 1:
        x = x.reshape(*lead, -1)
    return x if x.dtype == torch.float32 else x.float()


class Encoder(nn.Module):
    """Dict observation -> feature vector; features in sorted-key order, then image embeddings."""

    def __init__(
        self,
        observation_spec: ObservationSpec,
        torso_hidden: int = 64,
        torso_norm_elu: bool = True,
        channels: tuple[int, ...] = (16, 32, 32),
        blocks: tuple[int, ...] = (2, 2, 2),
    ) -> None:
        super().__init__()
        specs = _as_dict(observation_spec)
        self.feature_keys = sorted(k for k, s in specs.items() if not is_image(s))
        self.image_keys = sorted(k for k, s in specs.items() if is_image(s))
        self.feature_shapes = {k: specs[k].shape for k in self.feature_keys}
        torsos = [
            ResNetTorso(specs[k].shape, channels, blocks, torso_hidden, torso_norm_elu)
            for k in self.image_keys
        ]
        self.torsos = nn.ModuleList(torsos)
        self.output_dim = sum(specs[k].size for k in self.feature_keys) + sum(
            t.output_dim for t in torsos
        )
        if self.output_dim == 0:
            raise SpecError("observation spec has no entries; pass at least one ArraySpec")

    def flatten(self, obs: TensorObservation, batch_dims: int = 1) -> TensorObservation:
        """The feature vector ``forward`` would build, for an encoder without image keys (other
        encoders get ``obs`` back): an update that feeds one batch to several networks of the
        same observation spec concatenates its keys once and passes the tensor on."""
        return obs if self.image_keys else self(obs, batch_dims)

    def forward(self, obs: TensorObservation, batch_dims: int = 1) -> torch.Tensor:
        if not isinstance(obs, Mapping):
            if not self.image_keys:  # already the features: a flat spec, or flatten()
                return _flat_float(obs, batch_dims, obs.shape[:batch_dims])
            obs = {"": obs}
        first = obs[(self.feature_keys or self.image_keys)[0]]
        lead = first.shape[:batch_dims]
        parts = [_flat_float(obs[k], batch_dims, lead) for k in self.feature_keys]
        for key, torso in zip(self.image_keys, self.torsos, strict=True):
            img = obs[key]
            parts.append(torso(img.reshape(-1, *img.shape[batch_dims:])).reshape(*lead, -1))
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)


def cat_batches(*batches: TensorObservation) -> TensorObservation:
    """Batches of one spec joined along the batch dimension, so one network pass serves them all:
    tensors (``Encoder.flatten``'s features) or dicts of tensors with the same keys."""
    dicts = [b for b in batches if isinstance(b, Mapping)]
    tensors = [b for b in batches if not isinstance(b, Mapping)]
    if dicts and tensors:
        raise RluError("cat_batches: dicts and tensors of different specs (a bug in rlu)")
    if dicts:
        return {k: torch.cat([b[k] for b in dicts]) for k in dicts[0]}
    return torch.cat(tensors)


class ResidualMLP(nn.Module):
    """Linear projection, then ``num_layers // 2`` blocks h <- norm(h + W2 act(W1 act(h)))."""

    def __init__(self, input_dim: int, hidden: int = 1024, num_layers: int = 8) -> None:
        super().__init__()
        if num_layers < 2 or num_layers % 2:
            raise ValueError(f"ResidualMLP num_layers must be even and >= 2, got {num_layers}")
        self.inp = nn.Linear(input_dim, hidden)
        self.blocks = nn.ModuleList(
            nn.Sequential(nn.ELU(), nn.Linear(hidden, hidden), nn.ELU(), nn.Linear(hidden, hidden))
            for _ in range(num_layers // 2)
        )
        self.norms = nn.ModuleList(nn.LayerNorm(hidden) for _ in range(num_layers // 2))
        self.output_dim = hidden

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.inp(x)
        for block, norm in zip(self.blocks, self.norms, strict=True):
            h = norm(h + block(h))
        return F.elu(h)


_TRUNCATED_STD = 0.87962566103423978
"""Std of a unit normal truncated to [-2, 2]: Keras' ``VarianceScaling`` divides by it so its
truncated draws have the std ``sqrt(scale / fan)``."""


def truncated_normal_(weight: torch.Tensor, std: float) -> torch.Tensor:
    """TF's ``truncated_normal(shape, 0, std)`` in place: N(0, std^2) redrawn outside +-2 std
    (so the draws' std is 0.8796 std)."""
    return nn.init.trunc_normal_(weight, 0.0, std, -2.0 * std, 2.0 * std)


def variance_scaling_(
    weight: torch.Tensor, scale: float = 1.0, mode: str = "fan_in",
    distribution: str = "truncated_normal",
) -> torch.Tensor:  # fmt: skip
    """Keras' ``VarianceScaling(scale, mode, distribution)`` (``tf.initializers`` in TF2, what
    Acme's TF networks pass to Sonnet) on a torch ``(out, in)`` weight, in place. ``n`` is the
    fan of ``mode`` (fan_in = in, fan_out = out, fan_avg their mean); 'truncated_normal' draws
    ``truncated_normal_(sqrt(scale / n) / .8796)`` (std ``sqrt(scale / n)``), 'uniform'
    U(+-sqrt(3 scale / n)) (std ``sqrt(scale / n)``)."""
    fan_out, fan_in = weight.shape[0], weight[0].numel()
    n = {"fan_in": fan_in, "fan_out": fan_out, "fan_avg": (fan_in + fan_out) / 2}[mode]
    if distribution == "truncated_normal":
        return truncated_normal_(weight, (scale / n) ** 0.5 / _TRUNCATED_STD)
    if distribution == "uniform":
        limit = (3.0 * scale / n) ** 0.5
        return nn.init.uniform_(weight, -limit, limit)
    raise ValueError(f"variance_scaling_: unknown distribution {distribution!r}")


def layer_norm_mlp(
    input_dim: int, sizes: tuple[int, ...], activate_final: bool = True
) -> nn.Sequential:
    """Acme's LayerNormMLP: Linear -> LayerNorm -> tanh, then Linear -> ELU layers."""
    layers: list[nn.Module] = [nn.Linear(input_dim, sizes[0]), nn.LayerNorm(sizes[0]), nn.Tanh()]
    for i, size in enumerate(sizes[1:]):
        layers.append(nn.Linear(sizes[i], size))
        if activate_final or i < len(sizes) - 2:
            layers.append(nn.ELU())
    return nn.Sequential(*layers)


def mlp(
    input_dim: int, sizes: tuple[int, ...], output_dim: int, layer_norm: bool = False
) -> nn.Sequential:
    """Plain ReLU MLP (the BCQ and BRAC papers' networks); with ``layer_norm`` a LayerNorm after
    every hidden ReLU (Linear -> ReLU -> LayerNorm: ReBRAC's critic)."""
    layers: list[nn.Module] = []
    for size in sizes:
        layers += [nn.Linear(input_dim, size), nn.ReLU()]
        if layer_norm:
            layers.append(nn.LayerNorm(size))
        input_dim = size
    layers.append(nn.Linear(input_dim, output_dim))
    return nn.Sequential(*layers)


class Torso(nn.Module):
    """Encoder -> ResidualMLP -> optional two-layer LSTM; ``extra_dim`` joins the MLP input."""

    def __init__(
        self,
        observation_spec: ObservationSpec,
        hidden: int,
        num_layers: int,
        lstm_hidden: int = 0,
        extra_dim: int = 0,
        torso_hidden: int = 64,
        torso_norm_elu: bool = True,
    ) -> None:
        super().__init__()
        self.encoder = Encoder(observation_spec, torso_hidden, torso_norm_elu)
        self.mlp = ResidualMLP(self.encoder.output_dim + extra_dim, hidden, num_layers)
        self.lstm = (
            nn.LSTM(hidden, lstm_hidden, num_layers=2, batch_first=True) if lstm_hidden else None
        )
        self.output_dim = lstm_hidden or hidden

    def forward(
        self,
        obs: TensorObservation,
        extra: torch.Tensor | None = None,
        state: LSTMState | None = None,
        sequence: bool = False,
    ) -> tuple[torch.Tensor, LSTMState | None]:
        """(B, ...) -> (B, H), or with ``sequence`` (B, T, ...) -> (B, T, H) and the LSTM state."""
        h = self.encoder(obs, batch_dims=2 if sequence else 1)
        if extra is not None:
            h = torch.cat([h, extra], dim=-1)
        h = self.mlp(h)
        if self.lstm is None:
            return h, None
        if not sequence:  # one step of a rollout: (B, H) -> (B, 1, H)
            out, state = self.lstm(h.unsqueeze(1), state)
            return out.squeeze(1), state
        return self.lstm(h, state)


class MixtureHead(nn.Module):
    """Mixture of ``components`` diagonal Gaussians over the unit-scaled action."""

    def __init__(
        self, input_dim: int, action_dim: int, components: int = 5, min_std: float = 1e-3
    ) -> None:
        super().__init__()
        self.k, self.a, self.min_std = components, action_dim, min_std
        self.linear = nn.Linear(input_dim, components * (1 + 2 * action_dim))

    def forward(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        out = self.linear(h)
        logits = out[..., : self.k]
        rest = out[..., self.k :].reshape(*out.shape[:-1], self.k, 2, self.a)
        mean, std = rest[..., 0, :], F.softplus(rest[..., 1, :]) + self.min_std
        return logits, mean, std


class GaussianHead(nn.Module):
    """One diagonal Gaussian (RABM's prior and policy: MPO's update is built for Gaussians)."""

    def __init__(self, input_dim: int, action_dim: int, min_std: float = 1e-3) -> None:
        super().__init__()
        self.linear = nn.Linear(input_dim, 2 * action_dim)
        self.min_std = min_std

    def forward(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, raw = self.linear(h).chunk(2, dim=-1)
        return mean, F.softplus(raw) + self.min_std


class CategoricalHead(nn.Module):
    """Logits over ``num_atoms`` evenly spaced returns in [vmin, vmax] (C51 / D4PG)."""

    atoms: torch.Tensor  # a buffer

    def __init__(self, input_dim: int, num_atoms: int, vmin: float, vmax: float) -> None:
        super().__init__()
        self.linear = nn.Linear(input_dim, num_atoms)
        self.register_buffer("atoms", torch.linspace(vmin, vmax, num_atoms))

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return self.linear(h)

    def mean(self, logits: torch.Tensor) -> torch.Tensor:
        return (torch.softmax(logits, -1) * self.atoms).sum(-1)


class TwinCritic(nn.Module):
    """Two Q-networks on one encoder: Q_i(s, a) = MLP_i([Encoder(s), a]) (ReLU MLPs, with
    ``layer_norm`` a LayerNorm after every hidden ReLU)."""

    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_dim: int,
        layers: tuple[int, ...],
        torso_hidden: int,
        layer_norm: bool = False,
    ) -> None:
        super().__init__()
        self.encoder = Encoder(observation_spec, torso_hidden)
        f = self.encoder.output_dim + action_dim
        self.q1 = mlp(f, layers, 1, layer_norm)
        self.q2 = mlp(f, layers, 1, layer_norm)

    def forward(self, obs: TensorObservation, action: torch.Tensor) -> torch.Tensor:
        """(2, ...) values of (B, A) actions, or (N, B, A): N actions per state, one encoder
        pass."""
        s = self.encoder(obs)
        sa = torch.cat([s.expand(*action.shape[:-1], s.shape[-1]), action], -1)
        return torch.stack([self.q1(sa).squeeze(-1), self.q2(sa).squeeze(-1)])

    def first(self, obs: TensorObservation, action: torch.Tensor) -> torch.Tensor:
        """Q_1(s, a) alone, (B,): TD3's actor loss reads the first critic only, and a pass
        through both would also send its backward pass through the second."""
        return self.q1(torch.cat([self.encoder(obs), action], -1)).squeeze(-1)


class DeterministicPolicy(nn.Module):
    """a = tanh(MLP(Encoder(s))) in [-1, 1]: TD3's actor (TD3+BC, ReBRAC)."""

    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_dim: int,
        layers: tuple[int, ...],
        torso_hidden: int,
        layer_norm: bool = False,
    ) -> None:
        super().__init__()
        self.encoder = Encoder(observation_spec, torso_hidden)
        self.net = mlp(self.encoder.output_dim, layers, action_dim, layer_norm)

    def forward(self, obs: TensorObservation) -> torch.Tensor:
        return torch.tanh(self.net(self.encoder(obs)))


class ObservationNormaliser(nn.Module):
    """(x - mean) / (std + eps) per float observation entry, with a whole dataset's statistics
    (``rlu.types.DataStatistics``: the training loop computes them once and hands them to
    ``agent.set_statistics``) held as buffers, so they travel in the agent's state and move
    with it between devices. uint8 entries (cameras) pass unchanged: the data's statistics leave
    them out and their torso scales pixels itself. With ``enabled`` False every observation
    passes unchanged (the buffers stay, so the state has one layout).

    ``statistics`` is what the agent declares in its ``BatchSpec``; ``ready`` turns True once
    statistics are :meth:`set` or a state is loaded (a state carries its own), and
    :meth:`require` refuses an update before that: normalising with the initial mean 0 and
    std 1 would silently be another algorithm."""

    def __init__(self, observation_spec: ObservationSpec, eps: float, enabled: bool = True) -> None:
        super().__init__()
        specs = _as_dict(observation_spec)
        self.keys = sorted(k for k, s in specs.items() if np.dtype(s.dtype) != np.uint8)
        self.shapes = {k: tuple(specs[k].shape) for k in self.keys}
        self.eps, self.enabled, self.ready = float(eps), bool(enabled), not enabled
        self.statistics: tuple[str, ...] = ("observation",) if enabled else ()
        for i, key in enumerate(self.keys):  # buffer names by position: keys may hold "/"
            self.register_buffer(f"mean_{i}", torch.zeros(self.shapes[key]))
            self.register_buffer(f"std_{i}", torch.ones(self.shapes[key]))
        self.register_load_state_dict_post_hook(ObservationNormaliser._loaded)

    def _loaded(self, incompatible_keys: Any) -> None:
        self.ready = True

    def require(self, agent: str) -> None:
        """An ``RluError`` saying what to do if no statistics were set or loaded."""
        if not self.ready:
            raise RluError(
                f"{agent} normalises observations with the dataset's statistics and none were "
                "set: call agent.set_statistics(rlu.data.statistics.dataset_statistics(ds, "
                "agent.batch_spec.statistics)) before the first update (rlu train does)"
            )

    def set(self, stats: Any) -> None:
        """Take ``stats.observation_mean`` and ``stats.observation_std`` (arrays, or dicts of
        arrays by observation key); a missing entry, another shape or a value that is not
        finite is an ``RluError`` naming the entry."""
        means, stds = stats.observation_mean, stats.observation_std
        means = means if isinstance(means, Mapping) else {"": means}
        stds = stds if isinstance(stds, Mapping) else {"": stds}
        for i, key in enumerate(self.keys):
            for kind, values in (("mean", means), ("std", stds)):
                name = f"observation {kind}" + (f" of {key!r}" if key else "")
                if values.get(key) is None:
                    raise RluError(
                        f"the dataset statistics hold no {name}; compute them with "
                        "rlu.data.statistics.dataset_statistics(ds, agent.batch_spec.statistics)"
                    )
                value = np.asarray(values[key], np.float32)
                if value.shape != self.shapes[key] or not np.all(np.isfinite(value)):
                    raise RluError(
                        f"the {name} has shape {value.shape} or values that are not finite; "
                        f"the observation spec wants shape {self.shapes[key]}, finite values"
                    )
                self.get_buffer(f"{kind}_{i}").copy_(torch.from_numpy(value))
        self.ready = True

    def forward(self, obs: TensorObservation) -> TensorObservation:
        if not self.enabled:
            return obs
        if not isinstance(obs, Mapping):
            return self._normalised(0, obs) if self.keys == [""] else obs
        out = dict(obs)
        for i, key in enumerate(self.keys):
            out[key] = self._normalised(i, obs[key])
        return out

    def _normalised(self, i: int, x: torch.Tensor) -> torch.Tensor:
        return (x - self.get_buffer(f"mean_{i}")) / (self.get_buffer(f"std_{i}") + self.eps)


class TanhGaussianPolicy(nn.Module):
    """tanh(u), u ~ N(mean, std), with [mean, raw log std] = MLP(Encoder(s)) (ReLU MLP).

    ``log_std_range`` (lo, hi) bounds the log std: clipped to it (rlkit's SAC, CQL), or with
    ``squash_log_std`` mapped smoothly onto it, lo + (hi - lo) (tanh(raw) + 1) / 2 (BRAC's
    ``ActorNetwork``)."""

    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_dim: int,
        layers: tuple[int, ...],
        torso_hidden: int,
        log_std_range: tuple[float, float],
        squash_log_std: bool = False,
    ) -> None:
        super().__init__()
        self.encoder = Encoder(observation_spec, torso_hidden)
        self.net = mlp(self.encoder.output_dim, layers, 2 * action_dim)
        self.log_std_range, self.squash_log_std = log_std_range, squash_log_std

    def forward(self, obs: TensorObservation) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, std) of the pre-tanh Gaussian."""
        return self.dist(self.encoder(obs))

    def dist(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = self.net(features).chunk(2, -1)
        lo, hi = self.log_std_range
        if self.squash_log_std:
            log_std = lo + 0.5 * (hi - lo) * (torch.tanh(log_std) + 1.0)
        else:
            log_std = log_std.clamp(lo, hi)
        return mean, log_std.exp()

    def log_prob(
        self,
        obs: TensorObservation,
        action: torch.Tensor,
        clip: float,
        features: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """log pi(action | s) of (B, A) or (S, B, A) actions at (B, ...) states, the actions
        clipped to +-``clip`` first (atanh of exactly +-1 is infinite)."""
        mean, std = self.dist(self.encoder(obs) if features is None else features)
        return tanh_gaussian_log_prob(mean, std, torch.atanh(action.clamp(-clip, clip)))

    def sample(
        self, obs: TensorObservation, num: int, generator: torch.Generator
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(num, B, A) reparameterised actions and their (num, B) log densities."""
        mean, std = self(obs)
        return sample_tanh_gaussian(mean, std, num, generator)


def sample_tanh_gaussian(
    mean: torch.Tensor, std: torch.Tensor, num: int, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """(num, B, A) reparameterised actions tanh(mean + std eps) and their (num, B) log densities."""
    u = mean + std * torch.randn((num, *mean.shape), generator=generator, device=mean.device)
    return torch.tanh(u), tanh_gaussian_log_prob(mean, std, u)


def mixture_sample(
    logits: torch.Tensor,
    mean: torch.Tensor,
    std: torch.Tensor,
    generator: torch.Generator,
    std_override: float | None = None,
) -> torch.Tensor:
    """One action per row: a component drawn by weight, then Gaussian noise."""
    flat = torch.softmax(logits, -1).reshape(-1, logits.shape[-1])
    idx = torch.multinomial(flat, 1, generator=generator).reshape(*logits.shape[:-1], 1, 1)
    idx = idx.expand(*mean.shape[:-2], 1, mean.shape[-1])
    mu, sd = mean.gather(-2, idx).squeeze(-2), std.gather(-2, idx).squeeze(-2)
    if std_override is not None:
        sd = torch.full_like(sd, std_override)
    return mu + sd * torch.randn(mu.shape, generator=generator, device=mu.device)


def mixture_mode(logits: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
    """The mean of the most probable component (a mixture's deterministic action)."""
    idx = logits.argmax(-1)[..., None, None].expand(*mean.shape[:-2], 1, mean.shape[-1])
    return mean.gather(-2, idx).squeeze(-2)


class ActionScaler:
    """Maps the spec's [minimum, maximum] box to [-1, 1] and back; agents learn in [-1, 1]."""

    def __init__(self, spec: ActionSpec) -> None:
        if not isinstance(spec, BoundedSpec):
            raise SpecError(f"continuous agents need a BoundedSpec action spec, got {spec!r}")
        self.lo, self.hi, self.dim = float(spec.minimum), float(spec.maximum), spec.size
        self.shape, self.dtype = spec.shape, spec.dtype

    def to_unit(self, a: torch.Tensor) -> torch.Tensor:
        a = a.reshape(*a.shape[: a.dim() - len(self.shape)], self.dim).float()
        if self.lo != -1.0 or self.hi != 1.0:  # the control suite's box needs no affine map
            a = 2.0 * (a - self.lo) / (self.hi - self.lo) - 1.0
        return a.clamp(-1.0, 1.0)

    def from_unit(self, a: torch.Tensor) -> np.ndarray:
        a = (a.clamp(-1.0, 1.0) + 1.0) * 0.5 * (self.hi - self.lo) + self.lo
        a = a.clamp(self.lo, self.hi)  # float rounding can step just outside the box
        return a.reshape(*a.shape[:-1], *self.shape).cpu().numpy().astype(self.dtype)


def carried_state(
    state: LSTMState | None, is_first: np.ndarray | None, obs: TensorObservation
) -> LSTMState | None:
    """The LSTM state an acting step on ``obs`` continues from: None (zeros) where there is none
    or the batch changed size, and zeros in the rows whose episode starts now (``is_first``)."""
    batch = (next(iter(obs.values())) if isinstance(obs, Mapping) else obs).shape[0]
    if state is None or state[0].shape[1] != batch:
        return None
    if is_first is None:
        return state
    keep = torch.from_numpy(~np.asarray(is_first, bool).reshape(-1))[None, :, None]
    keep = keep.to(state[0].device)
    return tuple(s * keep for s in state)
