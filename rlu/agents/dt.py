"""Decision Transformer, DT (Chen et al. 2021, "Decision Transformer: Reinforcement Learning via
Sequence Modeling"), for continuous actions and for Atari. RL Unplugged's paper did not run DT:
rlu adds it beside the paper's baselines. Original code: ``kzl/decision-transformer`` at e2d82e6,
``gym/`` (continuous control, Hugging Face's GPT-2 without its position embeddings) and
``atari/`` (minGPT).

DT reads the last K steps as tokens (R_t, s_t, a_t) through a causal GPT, R_t the return to go
(the undiscounted sum of the rewards from step t to the episode's end, over ``return_scale``),
and predicts a_t from the output at s_t's token: a tanh action and mean squared error for
continuous actions, logits and cross-entropy for discrete ones. At evaluation the first R is
the target return and each later R the one before less the reward just earned
(``next_return_to_go``); the context is each row's last K steps, restarted where an episode
starts.

The action spec picks the settings. Continuous actions take the config's own fields, the gym
code's: K 20, 3 layers, 1 head, width 128, ReLU, dropout 0.1, a timestep embedding added to
every token, a LayerNorm over the token embeddings, states normalised by the data's mean and
std, returns / 1000, AdamW 1e-4 with weight decay 1e-4 on every parameter, 10,000 warm-up
steps, gradient norm 0.25, batch 64, 100,000 updates. Atari takes the ``atari`` field
(:class:`AtariDT`), the Atari code's: K 30 (Pong 50), 6 layers, 8 heads, width 128, GELU, the
Nature CNN, tanh embeddings, a global embedding of the window's first timestep plus a learnt
position per token, raw returns, AdamW 6e-4 with betas (0.9, 0.95) and weight decay 0.1 on the
matrix weights only, gradient norm 1.0, linear warm-up over 10,240 tokens then cosine decay to
10 % at ``final_tokens``, batch 128 (Pong 512), 5 epochs of the DT paper's 500,000 steps.
``paper_breakout``, ``paper_qbert``, ``paper_pong`` and ``paper_seaquest`` add the Atari code's
per-game targets (90, 14,000, 20 with K 50 and batch 512, 1,150).

Deviations and choices:
- Target return: ``target_return``; when None (``paper``), rlu's rule: ``target_multiplier``
  (1.0) times the best whole-episode return in the data (``DataStatistics.return_max``, asked
  for in ``batch_spec.statistics``). The DT paper's gym targets are for D4RL's tasks. The
  per-game presets hold the Atari code's targets, which its authors say come from an earlier
  version of the paper (kzl/decision-transformer#23: prefer its Table 8): rlu could not read
  Table 8 here, so they are the numbers the code ran; override ``atari.target_return``.
- Windows are the sequence views' (every start step equally likely, padded past a segment's
  end); padded steps and each episode's final step (RLDS: its action carries no information)
  are left out of the loss. The gym code draws episodes by length and left-pads, the Atari code
  shifts a window to end inside its episode. Under a causal mask, padding after the real steps
  leaves their outputs as they are without it, so no attention mask is needed.
- Timesteps (``Sequence.timestep``) count from the segment's first step: the episode's timestep
  for whole-episode data; a window file's segment (seq40) starts mid-episode, so for it
  ``timesteps="context"`` embeds each step's position in its window instead, at training and
  at evaluation alike. Later steps than ``max_timestep`` share its embedding (the gym code's).
- Atari: the global timestep is the context's first step's at evaluation as at training (the
  Atari code embeds the current step at evaluation). Returns to go are of the data's stored
  reward (raw game scores in generated and ``atari_episodes_ordered`` data), lowered at
  evaluation by the env's raw reward, so targets are raw scores; the Atari code trained on the
  DQN Replay logs' clipped rewards and lowered its target by raw ones. Its first update runs at
  the base learning rate (the code sets the rate after each update, from the B K tokens of the
  updates so far); rlu does the same (``learning_rate_multiplier``).
- Dropout (``nn.Dropout``, attention's) draws from torch's global generators: each update runs
  on a private copy of them seeded from the agent's own ``dropout`` generator, so the same seed
  gives the same run and the caller's generators are left alone.
- Cameras (locomotion): each image through BC's ResNet torso (``torso_hidden``), joined to the
  features before the state embedding; the DT paper has no camera task.
- Acting: ``greedy=True`` is the DT code's evaluation: the continuous action itself, and for
  Atari a sample of the softmax (the Atari code's ``sample=True``; ``atari.sample_actions=False``
  takes the argmax). ``greedy=False``: the continuous action too (DT's continuous policy is
  deterministic), a softmax sample for Atari. The context caches each step's state embedding
  (exact: nothing in the encoder is random at evaluation) and reruns the transformer on it.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from rlu.agents import common
from rlu.agents import discrete_common as dc
from rlu.agents import networks as nets
from rlu.files import (
    BATCH,
    LEARNING_RATE,
    MAX_LAYERS,
    MAX_STEPS,
    STEPS,
    WIDTH,
    Checked,
    bounds,
)
from rlu.seeds import stream_seed
from rlu.types import (
    ActionSpec,
    BatchSpec,
    DataStatistics,
    DiscreteSpec,
    Observation,
    ObservationSpec,
    RluError,
    Sequence,
)

TIMESTEPS = ("episode", "context")


@dataclass(frozen=True)
class AtariDT(Checked):
    """DT's settings for discrete actions (Atari), the ``atari`` field of :class:`DTConfig`:
    the DT Atari code's (``atari/run_dt_atari.py``, ``atari/mingpt``)."""

    context_length: int = field(default=30, metadata=bounds(min=1, max=10_000))
    """K: steps per training window and per acting context (the Atari code: 30, Pong 50)."""
    num_layers: int = field(default=6, metadata=bounds(min=1, max=MAX_LAYERS))
    """Transformer blocks."""
    num_heads: int = field(default=8, metadata=bounds(min=1, max=1024))
    """Attention heads per block."""
    hidden_size: int = field(default=128, metadata=WIDTH)
    """Width of the token embeddings and of the transformer (minGPT's n_embd)."""
    dropout: float = field(default=0.1, metadata=bounds(min=0.0, lt=1.0))
    """Dropout of the embeddings, the attention weights and both residual branches."""
    channels: tuple[int, ...] = field(
        default=(32, 64, 64), metadata=bounds(min=1, max=4096, min_len=1, max_len=16)
    )
    """Nature CNN output channels per convolution (then a linear layer to the width, tanh)."""
    kernel_sizes: tuple[int, ...] = field(
        default=(8, 4, 3), metadata=bounds(min=1, max=84, min_len=1, max_len=16)
    )
    """Nature CNN square filter sizes."""
    strides: tuple[int, ...] = field(
        default=(4, 2, 1), metadata=bounds(min=1, max=84, min_len=1, max_len=16)
    )
    """Nature CNN strides."""
    learning_rate: float = field(default=6e-4, metadata=LEARNING_RATE)
    """AdamW's base learning rate."""
    betas: tuple[float, float] = field(default=(0.9, 0.95), metadata=bounds(min=0.0, lt=1.0))
    """AdamW's betas."""
    weight_decay: float = field(default=0.1, metadata=bounds(min=0.0, max=1e3))
    """AdamW's weight decay of the linear and convolution weights (biases, LayerNorms,
    embeddings and position embeddings: none, minGPT's split)."""
    max_grad_norm: float = field(default=1.0, metadata=bounds(min=0.0, max=1e9))
    """Global gradient norm clip."""
    warmup_tokens: int = field(default=10_240, metadata=bounds(min=0, max=10**13))
    """Tokens (batch_size x context_length per update) of the linear learning-rate warm-up
    (the Atari code: 512 x 20)."""
    final_tokens: int = field(default=90_000_000, metadata=bounds(min=1, max=10**13))
    """Tokens at which the cosine decay reaches 10 % of the base rate (the Atari code:
    2 x its 500,000 steps x 3K)."""
    batch_size: int = field(default=128, metadata=BATCH)
    """Windows per update (the Atari code: 128, Pong 512)."""
    num_steps: int = field(default=19_530, metadata=STEPS)
    """Learner steps of a full run: 5 epochs of 3,906 batches of 128 over the DT paper's
    500,000 steps (Pong: 4,885 of 512); ``rlu train`` runs them without --steps."""
    max_timestep: int = field(default=27_000, metadata=bounds(min=1, max=10**7))
    """Largest timestep with its own global embedding (later ones share it); the env's cap of
    27,000 agent steps (the Atari code: its data's longest episode)."""
    return_scale: float = field(default=1.0, metadata=bounds(gt=0.0, max=1e9))
    """Returns to go are divided by it before their embedding (the Atari code: raw returns)."""
    target_return: float | None = field(default=None, metadata=bounds(min=-1e9, max=1e9))
    """The return the first step of an evaluation episode conditions on; None: rlu's rule,
    ``target_multiplier`` x the data's best whole-episode return (module docstring)."""
    target_multiplier: float = field(default=1.0, metadata=bounds(min=-1e3, max=1e3))
    """The rule's multiple of the data's best return (used when ``target_return`` is None)."""
    sample_actions: bool = True
    """Greedy acting samples the softmax (the Atari code's evaluation); False: the argmax."""


@dataclass(frozen=True)
class DTConfig(Checked):
    """DT's settings for continuous actions (the gym code's, ``gym/experiment.py``), and in
    ``atari`` those for discrete actions."""

    context_length: int = field(default=20, metadata=bounds(min=1, max=10_000))
    """K: steps per training window and per acting context."""
    num_layers: int = field(default=3, metadata=bounds(min=1, max=MAX_LAYERS))
    """Transformer blocks."""
    num_heads: int = field(default=1, metadata=bounds(min=1, max=1024))
    """Attention heads per block."""
    hidden_size: int = field(default=128, metadata=WIDTH)
    """Width of the token embeddings and of the transformer (the gym code's embed_dim)."""
    dropout: float = field(default=0.1, metadata=bounds(min=0.0, lt=1.0))
    """Dropout of the embeddings, the attention weights and both residual branches."""
    torso_hidden: int = field(default=64, metadata=WIDTH)
    """Embedding size of each camera's ResNet torso (camera observations only)."""
    normalize_observations: bool = True
    """States normalised by the data's mean and std (the gym code's; cameras pass unchanged)."""
    learning_rate: float = field(default=1e-4, metadata=LEARNING_RATE)
    """AdamW's learning rate after the warm-up."""
    betas: tuple[float, float] = field(default=(0.9, 0.999), metadata=bounds(min=0.0, lt=1.0))
    """AdamW's betas (PyTorch's default, as the gym code)."""
    weight_decay: float = field(default=1e-4, metadata=bounds(min=0.0, max=1e3))
    """AdamW's weight decay, on every parameter (the gym code's)."""
    max_grad_norm: float = field(default=0.25, metadata=bounds(min=0.0, max=1e9))
    """Global gradient norm clip."""
    warmup_steps: int = field(default=10_000, metadata=bounds(min=0, max=MAX_STEPS))
    """Updates of the linear learning-rate warm-up, ``min((step + 1) / warmup_steps, 1)``."""
    batch_size: int = field(default=64, metadata=BATCH)
    """Windows per update."""
    num_steps: int = field(default=100_000, metadata=STEPS)
    """Learner steps of a full run (the gym code: 10 iterations of 10,000); ``rlu train`` runs
    them without --steps."""
    timesteps: str = field(default="episode", metadata=bounds(choices=TIMESTEPS))
    """'episode': embed each step's timestep in its episode (the gym code); 'context': its
    position in the window, for window files whose segments start mid-episode (seq40)."""
    max_timestep: int = field(default=999, metadata=bounds(min=1, max=10**7))
    """Largest timestep with its own embedding, later ones share it (the gym code's 1,000
    entries of max_ep_len)."""
    return_scale: float = field(default=1000.0, metadata=bounds(gt=0.0, max=1e9))
    """Returns to go are divided by it before their embedding (the gym code: 1,000)."""
    target_return: float | None = field(default=None, metadata=bounds(min=-1e9, max=1e9))
    """The return the first step of an evaluation episode conditions on; None: rlu's rule,
    ``target_multiplier`` x the data's best whole-episode return (module docstring)."""
    target_multiplier: float = field(default=1.0, metadata=bounds(min=-1e3, max=1e3))
    """The rule's multiple of the data's best return (used when ``target_return`` is None)."""
    atari: AtariDT = field(default_factory=AtariDT)
    """The settings of discrete actions (Atari)."""


def _atari_game(context_length: int = 30, batch_size: int = 128, **kw: Any) -> DTConfig:
    """The paper preset with one game's Atari settings (the tokens and epochs scale with K, B)."""
    atari = AtariDT(
        context_length=context_length,
        batch_size=batch_size,
        final_tokens=2 * 500_000 * 3 * context_length,
        num_steps=5 * math.ceil((500_000 - 3 * context_length) / batch_size),
        **kw,
    )
    return DTConfig(atari=atari)  # fmt: skip


Config = DTConfig
PRESETS = {
    "paper": DTConfig(),
    # the Atari code's per-game settings (atari/run.sh, atari/mingpt/trainer_atari.py)
    "paper_breakout": _atari_game(target_return=90.0),
    "paper_qbert": _atari_game(target_return=14_000.0),
    "paper_pong": _atari_game(50, 512, target_return=20.0),
    "paper_seaquest": _atari_game(target_return=1_150.0),
    # minutes on a CPU: narrower, shorter contexts, a short warm-up, no dropout (it slowed the
    # first thousands of updates on the bundled cartpole data and costs a third of an update)
    "small": DTConfig(context_length=10, num_layers=2, hidden_size=64, dropout=0.0,
                      learning_rate=1e-3, warmup_steps=200, num_steps=5_000,
                      atari=AtariDT(context_length=8, num_layers=2, num_heads=4, hidden_size=64,
                                    dropout=0.0, channels=(16, 32, 32), batch_size=16,
                                    warmup_tokens=1_280, final_tokens=2_000_000, num_steps=5_000)),
}  # fmt: skip
GRID: dict[str, list] = {}  # the DT paper reports no sweep


# ------------------------------------------------------------------------------ the maths


def continuous_action_loss(
    predicted: torch.Tensor, action: torch.Tensor, weight: torch.Tensor
) -> tuple[torch.Tensor, common.Metrics]:
    """Mean squared error of the predicted actions over the weighted steps and the action
    dimensions (the gym code's ``mean((a_hat - a) ** 2)`` over its unpadded steps)."""
    error = ((predicted - action) ** 2).mean(-1)
    loss = (error * weight).sum() / weight.sum().clamp(min=1.0)
    return loss, {"actor/loss": loss}


def discrete_action_loss(
    logits: torch.Tensor, action: torch.Tensor, weight: torch.Tensor
) -> tuple[torch.Tensor, common.Metrics]:
    """Cross-entropy of the logits on the data's actions over the weighted steps."""
    nll = F.cross_entropy(
        logits.reshape(-1, logits.shape[-1]), action.reshape(-1), reduction="none"
    )
    total = weight.sum().clamp(min=1.0)
    loss = (nll * weight.reshape(-1)).sum() / total
    hit = (logits.argmax(-1) == action).float()
    return loss, {"actor/loss": loss, "actor/accuracy": (hit * weight).sum() / total}


def learning_rate_multiplier(step: int, settings: DTConfig | AtariDT) -> float:
    """The base learning rate's factor at update ``step`` (0 for the first).

    Continuous (the gym code's LambdaLR): ``min((step + 1) / warmup_steps, 1)``. Atari (the
    Atari code, which sets the rate after each update from the tokens seen): 1 at the first
    update, then with ``tokens = step x batch_size x context_length`` linear up to
    ``warmup_tokens`` and a cosine down to 0.1 at ``final_tokens``, 0.1 after (the code's
    cosine rises again past ``final_tokens``, which its 5 epochs never reach)."""
    if isinstance(settings, DTConfig):
        return min((step + 1) / settings.warmup_steps, 1.0)
    if step == 0:
        return 1.0
    tokens = step * settings.batch_size * settings.context_length
    if tokens < settings.warmup_tokens:
        return tokens / max(1, settings.warmup_tokens)
    span = max(1, settings.final_tokens - settings.warmup_tokens)
    progress = min(1.0, (tokens - settings.warmup_tokens) / span)  # the code's cosine would rise
    return max(0.1, 0.5 * (1.0 + math.cos(math.pi * progress)))  # again past final_tokens


def next_return_to_go(
    previous: torch.Tensor,
    reward: torch.Tensor,
    first: torch.Tensor,
    target: float | torch.Tensor,
    scale: float,
) -> torch.Tensor:
    """The return to go a step conditions on: the target (a number or a 0-d tensor) where its
    episode starts, else the previous step's less the reward just earned (both over ``scale``)."""
    target = torch.as_tensor(target, dtype=previous.dtype, device=previous.device)
    return torch.where(first, target / scale, previous - reward / scale)


def interleave(returns: torch.Tensor, states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """(B, T, H) token embeddings of R, s, a -> (B, 3T, H) in the order R_1, s_1, a_1, R_2, ..."""
    b, t, h = states.shape
    return torch.stack((returns, states, actions), dim=2).reshape(b, 3 * t, h)


# ------------------------------------------------------------------------------ networks


class Block(nn.Module):
    """A GPT-2 block: x + attention(LayerNorm(x)), then x + MLP(LayerNorm(x)), causal."""

    def __init__(self, width: int, heads: int, dropout: float, activation: type[nn.Module]) -> None:
        super().__init__()
        self.heads, self.dropout = heads, dropout
        self.ln_1, self.ln_2 = nn.LayerNorm(width), nn.LayerNorm(width)
        self.qkv, self.proj = nn.Linear(width, 3 * width), nn.Linear(width, width)
        self.mlp = nn.Sequential(
            nn.Linear(width, 4 * width), activation(), nn.Linear(4 * width, width)
        )
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, w = x.shape
        q, k, v = self.qkv(self.ln_1(x)).view(b, n, 3, self.heads, w // self.heads).unbind(2)
        p = self.dropout if self.training else 0.0
        y = F.scaled_dot_product_attention(
            q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2), dropout_p=p, is_causal=True
        )
        x = x + self.drop(self.proj(y.transpose(1, 2).reshape(b, n, w)))
        return x + self.drop(self.mlp(self.ln_2(x)))


class GPT(nn.Module):
    """Dropout on the input tokens, the blocks, a final LayerNorm (both DT codes' GPT, without
    GPT-2's own position embeddings: DT adds its own)."""

    def __init__(
        self, width: int, layers: int, heads: int, dropout: float, activation: type[nn.Module]
    ) -> None:
        super().__init__()
        if width % heads:
            raise RluError(f"dt: hidden_size {width} is not a multiple of num_heads {heads}")
        self.drop = nn.Dropout(dropout)
        self.blocks = nn.Sequential(*(Block(width, heads, dropout, activation)
                                      for _ in range(layers)))  # fmt: skip
        self.ln_f = nn.LayerNorm(width)
        self.apply(_gpt_init)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        return self.ln_f(self.blocks(self.drop(tokens)))


def _gpt_init(module: nn.Module) -> None:
    """Both codes' GPT initialisation: linear weights N(0, 0.02), biases 0, LayerNorms 1 and 0."""
    if isinstance(module, nn.Linear):
        nn.init.normal_(module.weight, 0.0, 0.02)
        nn.init.zeros_(module.bias)
    elif isinstance(module, nn.LayerNorm):
        nn.init.ones_(module.weight)
        nn.init.zeros_(module.bias)


class ContinuousDT(nn.Module):
    """The gym code's DecisionTransformer: linear embeddings of R, s and a plus a timestep
    embedding on each, a LayerNorm, the GPT, a tanh action from each state token."""

    target_return: torch.Tensor  # a buffer

    def __init__(self, observation_spec: ObservationSpec, action_dim: int, c: DTConfig) -> None:
        super().__init__()
        h = c.hidden_size
        self.normaliser = nets.ObservationNormaliser(observation_spec, 1e-6,
                                                     c.normalize_observations)  # fmt: skip
        self.encoder = nets.Encoder(observation_spec, c.torso_hidden)
        self.embed_state = nn.Linear(self.encoder.output_dim, h)
        self.embed_return, self.embed_action = nn.Linear(1, h), nn.Linear(action_dim, h)
        rows = c.context_length if c.timesteps == "context" else c.max_timestep + 1
        self.embed_timestep = nn.Embedding(rows, h)
        self.embed_ln = nn.LayerNorm(h)
        self.transformer = GPT(h, c.num_layers, c.num_heads, c.dropout, nn.ReLU)
        self.predict_action = nn.Linear(h, action_dim)
        self.register_buffer("target_return", torch.zeros(()))

    def state_tokens(self, observation: common.TensorObservation, batch_dims: int) -> torch.Tensor:
        return self.embed_state(self.encoder(self.normaliser(observation), batch_dims))

    def forward(
        self,
        states: torch.Tensor,
        actions: torch.Tensor,
        returns: torch.Tensor,
        timesteps: torch.Tensor,
    ) -> torch.Tensor:
        """(B, T, H) state tokens, (B, T, A) actions in [-1, 1], (B, T) returns to go (scaled),
        (B, T) timesteps -> (B, T, A) predicted actions."""
        time = self.embed_timestep(timesteps)
        tokens = interleave(self.embed_return(returns[..., None]) + time, states + time,
                            self.embed_action(actions) + time)  # fmt: skip
        out = self.transformer(self.embed_ln(tokens))
        return torch.tanh(self.predict_action(out[:, 1::3]))


class AtariDTModel(nn.Module):
    """The Atari code's GPT: Nature CNN + linear + tanh for s, linear + tanh for R, an embedding
    + tanh for a; a global embedding of the window's first timestep and a learnt position per
    token; logits from each state token."""

    target_return: torch.Tensor  # a buffer

    def __init__(self, frame_shape: dc.Shape, num_actions: int, c: AtariDT) -> None:
        super().__init__()
        h = c.hidden_size
        self.transformer = GPT(h, c.num_layers, c.num_heads, c.dropout, nn.GELU)
        self.head = nn.Linear(h, num_actions, bias=False)
        nn.init.normal_(self.head.weight, 0.0, 0.02)
        self.position = nn.Parameter(torch.zeros(3 * c.context_length, h))
        self.global_position = nn.Parameter(torch.zeros(c.max_timestep + 1, h))
        torso = dc.NatureTorso(tuple(frame_shape), c)  # type: ignore[arg-type]
        self.embed_state = nn.Sequential(torso, nn.Linear(torso.output_size, h), nn.Tanh())
        self.embed_return = nn.Sequential(nn.Linear(1, h), nn.Tanh())
        embedding = nn.Embedding(num_actions, h)
        self.embed_action = nn.Sequential(embedding, nn.Tanh())
        nn.init.normal_(embedding.weight, 0.0, 0.02)
        self.register_buffer("target_return", torch.zeros(()))

    def state_tokens(self, frames: torch.Tensor, batch_dims: int) -> torch.Tensor:
        lead = frames.shape[:batch_dims]
        return self.embed_state(frames.reshape(-1, *frames.shape[batch_dims:])).view(*lead, -1)

    def forward(
        self,
        states: torch.Tensor,
        actions: torch.Tensor,
        returns: torch.Tensor,
        timesteps: torch.Tensor,
    ) -> torch.Tensor:
        """(B, T, H) state tokens, (B, T) actions, (B, T) returns to go (scaled), (B, T)
        timesteps -> (B, T, num_actions) logits."""
        t = states.shape[1]
        tokens = interleave(self.embed_return(returns[..., None]), states,
                            self.embed_action(actions))  # fmt: skip
        where = self.global_position[timesteps[:, 0]][:, None] + self.position[: 3 * t]
        return self.head(self.transformer(tokens + where)[:, 1::3])


def decay_groups(model: nn.Module, weight_decay: float) -> list[dict[str, Any]]:
    """minGPT's parameter groups: weight decay on linear and convolution weights only."""
    decay: list[nn.Parameter] = []
    rest: list[nn.Parameter] = []
    for module in model.modules():
        for name, p in module.named_parameters(recurse=False):
            matrix = name == "weight" and isinstance(module, nn.Linear | nn.Conv2d)
            (decay if matrix else rest).append(p)
    return [{"params": decay, "weight_decay": weight_decay}, {"params": rest, "weight_decay": 0.0}]


@contextlib.contextmanager
def dropout_stream(generator: torch.Generator, device: torch.device) -> Iterator[None]:
    """Run ``nn.Dropout`` and attention dropout (which draw from torch's global generators) on a
    private copy of those generators, seeded from ``generator``; the caller's are left alone."""
    seed = int(torch.randint(0, 2**62, (), generator=generator, device=generator.device))
    cuda = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=cuda):
        torch.default_generator.manual_seed(seed)
        if cuda:
            torch.cuda.default_generators[cuda[0]].manual_seed(seed)
        yield


class Context(NamedTuple):
    """Each acting row's last K steps, oldest first, ``length`` of them real (later slots are
    stale and, under the causal mask, never read)."""

    states: torch.Tensor  # (N, K, H) state tokens
    actions: torch.Tensor  # (N, K, A) unit actions, or (N, K) action indices
    returns: torch.Tensor  # (N, K) scaled returns to go
    timesteps: torch.Tensor  # (N, K)
    length: torch.Tensor  # (N,)


def push(
    ctx: Context,
    state: torch.Tensor,
    ret: torch.Tensor,
    timestep: torch.Tensor,
    first: torch.Tensor,
) -> tuple[Context, torch.Tensor]:
    """The context with one more step per row (rows where ``first`` restart empty, full rows
    drop their oldest step) and the slot that step is in."""
    length = torch.where(first, torch.zeros_like(ctx.length), ctx.length)
    full = length == ctx.states.shape[1]

    def shifted(buf: torch.Tensor) -> torch.Tensor:
        keep = full.view(-1, *([1] * (buf.dim() - 1)))
        return torch.where(keep, buf.roll(-1, dims=1), buf)

    slot = length.clamp(max=ctx.states.shape[1] - 1)
    rows = torch.arange(len(slot), device=slot.device)
    states, actions, returns, timesteps = (
        shifted(b) for b in (ctx.states, ctx.actions, ctx.returns, ctx.timesteps)
    )
    states[rows, slot], returns[rows, slot], timesteps[rows, slot] = state, ret, timestep
    actions[rows, slot] = 0  # a_t follows s_t: the causal mask hides it from a_t's prediction
    length = (length + 1).clamp(max=ctx.states.shape[1])
    return Context(states, actions, returns, timesteps, length), slot


# ------------------------------------------------------------------------------ the agent


class DTAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: DTConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.discrete = isinstance(action_spec, DiscreteSpec)
        s = self.settings = config.atari if self.discrete else config
        _check(s, self.discrete)
        if self.discrete:
            frame_shape, self.num_actions = dc.check_specs("dt", observation_spec, action_spec)
        else:
            self.scaler = nets.ActionScaler(action_spec)
        self.episode_timesteps = self.discrete or config.timesteps == "episode"
        wants: tuple[str, ...] = ()
        if not self.discrete and config.normalize_observations:
            wants = ("observation",)
        wants += ("return",) if s.target_return is None else ()
        self.batch_spec = BatchSpec(s.batch_size, "sequence", sequence_length=s.context_length,
                                    return_to_go=True, timestep=self.episode_timesteps,
                                    statistics=wants)  # fmt: skip
        self.num_steps, self.pretrain_steps = s.num_steps, 0
        act_seed, dropout_seed = stream_seed(seed, "act"), stream_seed(seed, "dropout")
        with common.seeded(seed):
            if self.discrete:
                model: AtariDTModel | ContinuousDT
                model = AtariDTModel(frame_shape, self.num_actions, config.atari)
            else:
                model = ContinuousDT(observation_spec, self.scaler.dim, config)
            if s.target_return is not None:
                model.target_return.fill_(float(s.target_return))
            self.model = model.to(self.device)
        groups = (
            decay_groups(self.model, s.weight_decay)
            if self.discrete
            else [{"params": list(self.model.parameters()), "weight_decay": s.weight_decay}]
        )
        fused = all(p.device.type in ("cpu", "cuda") for p in self.model.parameters())
        self.modules = {"model": self.model}
        self.optimizers = {"model": torch.optim.AdamW(groups, lr=s.learning_rate, betas=s.betas,
                                                      fused=fused or None)}  # fmt: skip
        self.generators = {
            "act": common.generator(act_seed, self.device),
            "dropout": common.generator(dropout_seed, torch.device("cpu")),
        }
        self._target_ready = s.target_return is not None
        self._context: Context | None = None

    def set_statistics(self, stats: DataStatistics) -> None:
        """The data's observation mean and std (continuous, when normalising) and, for the
        target rule, its best whole-episode return."""
        s = self.settings
        if isinstance(self.model, ContinuousDT) and self.config.normalize_observations:
            self.model.normaliser.set(stats)
        if s.target_return is None:
            if stats.return_max is None:
                raise RluError(
                    "dt conditions on a target return, and with target_return=None it takes "
                    "target_multiplier x the data's best whole-episode return, but the data "
                    "holds no whole episode; set the target: `rlu train ... "
                    f"{'atari.' if self.discrete else ''}target_return=VALUE`"
                )
            self.model.target_return.fill_(s.target_multiplier * float(stats.return_max))
            self._target_ready = True

    def set_target(self, value: float) -> None:
        """Condition the episodes that start from now on on the return ``value`` (the DT paper
        evaluates several targets); the target travels in the agent's state."""
        self.model.target_return.fill_(float(value))
        self._target_ready = True

    def _batch(
        self, batch: Sequence
    ) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        # the observation is to_torch's: a tensor (frames, flat states) or a dict of tensors
        if batch.return_to_go is None or (self.episode_timesteps and batch.timestep is None):
            raise RluError(
                "dt learns from sequence batches with return_to_go (and timestep, unless "
                "timesteps='context'); sample them with rlu.data.make_sampler(ds, "
                "agent.batch_spec)"
            )
        d, s = self.device, self.settings
        mask = common.to_torch(batch.mask, d)
        weight = (mask & ~common.to_torch(batch.is_last, d)).float()
        returns = common.to_torch(batch.return_to_go, d, "float32") / s.return_scale
        if self.episode_timesteps:
            timesteps = common.to_torch(batch.timestep, d, "int64").clamp(max=s.max_timestep)
        else:
            timesteps = torch.arange(mask.shape[1], device=d).expand(mask.shape)
        obs = common.to_torch(batch.observation, d)
        if self.discrete:
            action = common.to_torch(batch.action, d, "int64").clamp(0, self.num_actions - 1)
        else:
            action = self.scaler.to_unit(common.to_torch(batch.action, d))
        return obs, action, returns, timesteps, weight

    def update(self, batch: Sequence) -> dict[str, float]:
        if isinstance(self.model, ContinuousDT):  # not self.discrete
            self.model.normaliser.require("dt")
        obs, action, returns, timesteps, weight = self._batch(batch)
        self.model.train()
        with dropout_stream(self.generators["dropout"], self.device):
            out = self.model(self.model.state_tokens(obs, 2), action, returns, timesteps)
        if self.discrete:
            loss, metrics = discrete_action_loss(out, action, weight)
        else:
            loss, metrics = continuous_action_loss(out, action, weight)
        lr = self.settings.learning_rate * learning_rate_multiplier(self.step, self.settings)
        for group in self.optimizers["model"].param_groups:
            group["lr"] = lr
        common.sgd_step(self.optimizers["model"], loss, max_norm=self.settings.max_grad_norm)
        self.step += 1
        metrics["actor/learning_rate"] = torch.tensor(lr, device=self.device)
        return common.metrics_to_floats(metrics)

    @torch.inference_mode()
    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """The action each row's context predicts (the continuous action; for Atari a softmax
        sample, or the argmax with ``atari.sample_actions=False`` when greedy); ``reward`` (what
        each row's previous action earned) lowers its return to go, so a row that goes on
        (``is_first`` False) needs it."""
        if not self._target_ready:
            raise RluError(
                "dt has no target return yet: call agent.set_statistics(...) (rlu train does) "
                "or load a trained state, or set target_return"
            )
        s, d = self.settings, self.device
        obs = common.to_torch(observation, d)
        n = (next(iter(obs.values())) if isinstance(obs, dict) else obs).shape[0]
        ctx = self._context
        if ctx is None or ctx.length.shape[0] != n:
            ctx, first_np = self._empty(n), np.ones(n, bool)
        else:
            first_np = np.zeros(n, bool) if is_first is None else np.asarray(is_first, bool)
        if reward is None and not first_np.all():
            raise RluError(
                "dt lowers each row's return to go by the reward of its previous action: pass "
                "act(..., is_first=..., reward=...) (the rollout's Policy gets both)"
            )
        first = torch.from_numpy(first_np.reshape(-1).copy()).to(d)
        r = torch.zeros(n, device=d) if reward is None else common.to_torch(reward, d, "float32")
        last = (ctx.length - 1).clamp(min=0)
        rows = torch.arange(n, device=d)
        ret = next_return_to_go(ctx.returns[rows, last], r.reshape(-1), first,
                                self.model.target_return, s.return_scale)  # fmt: skip
        timestep = torch.where(first, torch.zeros_like(last), ctx.timesteps[rows, last] + 1)
        self.model.eval()
        state = self.model.state_tokens(obs, 1)
        ctx, slot = push(ctx, state, ret, timestep, first)
        if self.episode_timesteps:
            timesteps = ctx.timesteps.clamp(max=s.max_timestep)
        else:
            timesteps = torch.arange(s.context_length, device=d).expand(n, -1)
        out = self.model(ctx.states, ctx.actions, ctx.returns, timesteps)[rows, slot]
        if self.discrete:
            if greedy and not self.config.atari.sample_actions:
                action = out.argmax(-1)
            else:
                action = torch.multinomial(out.softmax(-1), 1, generator=self.generators["act"])
                action = action.squeeze(-1)
            ctx.actions[rows, slot] = action
            self._context = ctx
            return action.cpu().numpy().astype(np.int64)
        ctx.actions[rows, slot] = out
        self._context = ctx
        return self.scaler.from_unit(out)

    def _empty(self, n: int) -> Context:
        s, d = self.settings, self.device
        k, h = s.context_length, s.hidden_size
        actions = (torch.zeros(n, k, dtype=torch.int64, device=d) if self.discrete
                   else torch.zeros(n, k, self.scaler.dim, device=d))  # fmt: skip
        return Context(torch.zeros(n, k, h, device=d), actions, torch.zeros(n, k, device=d),
                       torch.zeros(n, k, dtype=torch.int64, device=d),
                       torch.zeros(n, dtype=torch.int64, device=d))  # fmt: skip

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)
        self._target_ready, self._context = True, None  # acting restarts after a restore


def _check(s: DTConfig | AtariDT, discrete: bool) -> None:
    """Config values that would fail later or train something else, as errors naming them."""
    where = "atari." if discrete else ""
    checks = [
        ("context_length", s.context_length >= 1, "at least 1"),
        ("num_layers", s.num_layers >= 1, "at least 1"),
        ("num_heads", s.num_heads >= 1 and s.hidden_size % s.num_heads == 0,
         f"a divisor of hidden_size {s.hidden_size}"),
        ("dropout", 0.0 <= s.dropout < 1.0, "in [0, 1)"),
        ("return_scale", s.return_scale > 0, "positive"),
        ("max_timestep", s.max_timestep >= 0, "at least 0"),
        ("batch_size", s.batch_size >= 1, "at least 1"),
    ]  # fmt: skip
    if isinstance(s, DTConfig):
        checks += [("timesteps", s.timesteps in TIMESTEPS, f"one of {', '.join(TIMESTEPS)}"),
                   ("warmup_steps", s.warmup_steps >= 1, "at least 1")]  # fmt: skip
    for name, ok, want in checks:
        if not ok:
            raise RluError(f"dt config {where}{name}={getattr(s, name)!r}; use a value {want}")


Agent = DTAgent
