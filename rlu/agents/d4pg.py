"""D4PG run offline (Barth-Maron et al. 2018; paper appendix A.1, "D4PG").

The paper uses Acme's D4PG "following their network architectures and hyper-parameters" with
Adam 1e-4 for both networks and batch 256. Acme's networks (``examples/control_suite/
run_d4pg.py``): policy LayerNormMLP(256, 256, 256) -> linear -> tanh, critic on [observation,
action] LayerNormMLP(512, 512, 256) -> 51 logits over returns in [-150, 150]; camera images go
through the ResNet torso with 512 ReLU units (table 5).

The learner is Acme's ``D4PGLearner`` (``acme/agents/tf/d4pg/learning.py``) as RL Unplugged's
D4PG notebook runs it offline (``rl_unplugged/dm_control_suite_d4pg.ipynb``, deepmind-research):
on the release's 2-step windows turned into 1-step SARSA tuples (``dm_control_suite.py``,
``_build_sarsa_example``: r_t = reward[0], p_t = discount[0]), with ``discount=0.99`` and
``target_update_period=100`` and the learner's other defaults: ``clipping=True`` (each network's
gradient clipped to a global norm of 40, and dQ/da clipped per example to norm 1 in the policy
gradient, ``acme/tf/losses/dpg.py``). So the ``paper`` preset learns from 1-step transitions:
Acme's online agent (``agents/tf/d4pg/agent.py``) adds 5-step transitions to its replay
(``n_step=5``), which no 2-step window of the release can give. As the learner, one update
computes the critic's and the policy's gradients from the same parameters before either steps,
and the policy is trained at the batch's next observations (``dpg_a_t = policy(o_t)``).

Batches are n-step Transitions from the data layer (``n_step`` > 1 needs whole episodes, e.g.
the ``*_episodes`` families): ``reward`` is the gamma-discounted n-step sum (``gamma`` below is
the gamma it must use), ``discount`` the product of per-step discounts; the agent bootstraps
with gamma^n * discount.

Initialisation (``init="acme"``, the default): Acme's. ``acme/tf/networks/continuous.py``:
every linear layer of ``LayerNormMLP`` is ``VarianceScaling(0.333, fan_out, uniform)``
(U(+-sqrt(0.999 / fan_out)), std sqrt(0.333 / fan_out)), the policy's last layer is
``NearZeroInitializedLinear``: ``VarianceScaling(1e-4)`` (truncated normal, fan_in: std
sqrt(1e-4 / fan_in), about 0.01 / sqrt(fan_in)); ``distributional.py``: the critic's
``DiscreteValuedHead`` is a plain ``snt.Linear`` (Sonnet's default: truncated normal of std
1 / sqrt(fan_in) before truncation); Sonnet's biases start at 0 and its LayerNorm at scale 1,
offset 0. ``init="torch"`` is rlu's earlier initialisation, kept because the bundled dataset's
behaviour agents were built with it (the ``laptop`` generation scale sets it; rlu.generate.scales).

Deviations: offline, so no exploration noise. The ``small`` preset keeps clipping off and
``init="torch"`` (rlu's choices: its learning rates were chosen with both). The camera
ResNet torso keeps torch's default initialisation under either ``init``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents import networks as nets
from rlu.agents.losses import bootstrap_values, categorical_cross_entropy, categorical_projection
from rlu.files import (
    BATCH,
    FRACTION,
    LAYERS,
    LEARNING_RATE,
    STEPS,
    WIDTH,
    Checked,
    bounds,
)
from rlu.seeds import stream_seed
from rlu.types import ActionSpec, BatchSpec, Observation, ObservationSpec, RluError, Transition


@dataclass(frozen=True)
class D4PGConfig(Checked):
    policy_layers: tuple[int, ...] = field(
        default=(256, 256, 256),
        metadata=LAYERS,
    )
    """Acme's policy LayerNormMLP sizes."""
    critic_layers: tuple[int, ...] = field(
        default=(512, 512, 256),
        metadata=LAYERS,
    )
    """Acme's critic LayerNormMLP sizes."""
    torso_hidden: int = field(default=512, metadata=WIDTH)
    """Camera ResNet embedding size (table 5, D4PG column: 512, ReLU)."""
    num_atoms: int = field(default=51, metadata=bounds(min=2, max=10_000))
    """Atoms of the categorical critic (table 5, D4PG: 51)."""
    vmin: float = field(default=-150.0, metadata=bounds(min=-1e9, max=1e9))
    """Lowest atom (table 5, D4PG: -150)."""
    vmax: float = field(default=150.0, metadata=bounds(min=-1e9, max=1e9))
    """Highest atom (table 5, D4PG: 150)."""
    gamma: float = field(default=0.99, metadata=FRACTION)
    """Per-step discount; the data layer's n-step reward must be discounted with this gamma."""
    n_step: int = field(default=1, metadata=bounds(min=1, max=1000))
    """Steps of the n-step return: 1, as the RL Unplugged notebook's learner sees the release's
    windows (Acme's online agent uses 5; the release's 2-step windows hold one transition)."""
    target_update_period: int = field(default=100, metadata=STEPS)
    """Learner steps between hard copies into the target networks (the notebook's 100)."""
    policy_lr: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the policy (the paper: 1e-4 for both, Acme's default)."""
    critic_lr: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the critic."""
    max_grad_norm: float = field(default=40.0, metadata=bounds(min=0.0, max=1e9))
    """Global-norm clip of the critic's and of the policy's gradient, each on its own (Acme's
    learner with ``clipping=True``: ``tf.clip_by_global_norm(..., 40.)``); 0: none."""
    dqda_clip_norm: float = field(default=1.0, metadata=bounds(min=0.0, max=1e9))
    """Per-example norm clip of dQ/da in the policy gradient (Acme's ``losses.dpg`` with
    ``dqda_clipping=1.0, clip_norm=True``, on with ``clipping=True``); 0: none."""
    batch_size: int = field(default=256, metadata=BATCH)
    """Transitions per update."""
    num_steps: int = field(default=1_000_000, metadata=STEPS)
    """Learner steps of a full run: what ``rlu train`` runs when no --steps is given. The paper
    states no budget for the continuous baselines; 1M is rlu's choice."""
    init: Literal["acme", "torch"] = "acme"
    """How the weights start. 'acme': Acme's (the module's docstring): the LayerNormMLPs'
    layers U(+-sqrt(0.999 / fan_out)), the policy's last layer truncated normal of std
    sqrt(1e-4 / fan_in), the critic head's truncated normal of std 1 / sqrt(fan_in) before
    truncation, biases 0. 'torch': rlu's earlier init, which the bundled dataset's behaviour
    agents used: torch's default ``nn.Linear`` (weights and biases U(+-1 / sqrt(fan_in))) with
    the policy's last weight times 1e-4 (std 5.8e-5 / sqrt(fan_in), 170x below Acme's) and its
    bias 0."""


Config = D4PGConfig
PRESETS = {
    "paper": D4PGConfig(),
    # Clipping off and rlu's earlier init: the small preset's learning rates were chosen with
    # both (with init="acme" its 2,000-update learning check on the bundled cartpole swingup gave
    # 75.9 against a bar of 129.7, seed 0, measured 2026-12-03).
    "small": D4PGConfig(policy_layers=(256, 256), critic_layers=(256, 256), torso_hidden=64,
                        vmin=-100.0, vmax=100.0, policy_lr=3e-4, critic_lr=3e-4,
                        max_grad_norm=0.0, dqda_clip_norm=0.0, num_steps=20_000, init="torch"),
}  # fmt: skip
GRID: dict[str, list] = {}  # the paper reports no sweep for D4PG


def acme_layer_norm_mlp_init_(mlp: nn.Sequential) -> None:
    """Acme's ``LayerNormMLP`` initialisation, in place: every linear layer
    ``VarianceScaling(0.333, fan_out, uniform)`` with zero biases; LayerNorm scale 1, offset 0
    (torch's default, as Sonnet's)."""
    for layer in mlp:
        if isinstance(layer, nn.Linear):
            nets.variance_scaling_(layer.weight, 0.333, "fan_out", "uniform")
            layer.bias.zero_()


class Policy(nn.Module):
    def __init__(
        self, observation_spec: ObservationSpec, action_dim: int, config: D4PGConfig
    ) -> None:
        super().__init__()
        self.encoder = nets.Encoder(observation_spec, config.torso_hidden, torso_norm_elu=False)
        self.mlp = nets.layer_norm_mlp(self.encoder.output_dim, config.policy_layers)
        self.out = nn.Linear(config.policy_layers[-1], action_dim)
        with torch.no_grad():
            if config.init == "acme":  # LayerNormMLP, then NearZeroInitializedLinear
                acme_layer_norm_mlp_init_(self.mlp)
                nets.variance_scaling_(self.out.weight, 1e-4, "fan_in", "truncated_normal")
            else:  # rlu's earlier init (the bundled data's behaviour agents)
                self.out.weight.mul_(1e-4)
            self.out.bias.zero_()

    def forward(self, obs: common.TensorObservation) -> torch.Tensor:
        return torch.tanh(self.out(self.mlp(self.encoder(obs))))


class Critic(nn.Module):
    def __init__(
        self, observation_spec: ObservationSpec, action_dim: int, config: D4PGConfig
    ) -> None:
        super().__init__()
        self.encoder = nets.Encoder(observation_spec, config.torso_hidden, torso_norm_elu=False)
        self.mlp = nets.layer_norm_mlp(self.encoder.output_dim + action_dim, config.critic_layers)
        self.head = nets.CategoricalHead(
            config.critic_layers[-1], config.num_atoms, config.vmin, config.vmax
        )
        if config.init == "acme":  # LayerNormMLP, then DiscreteValuedHead's snt.Linear
            with torch.no_grad():
                acme_layer_norm_mlp_init_(self.mlp)
                linear = self.head.linear
                nets.truncated_normal_(linear.weight, linear.in_features**-0.5)
                linear.bias.zero_()

    def forward(self, obs: common.TensorObservation, action: torch.Tensor) -> torch.Tensor:
        return self.head(self.mlp(torch.cat([self.encoder(obs), action], -1)))


def critic_loss(
    logits: torch.Tensor,
    target_logits: torch.Tensor,
    reward: torch.Tensor,
    discount: torch.Tensor,
    atoms: torch.Tensor,
    bootstrap_gamma: float,
) -> tuple[torch.Tensor, common.Metrics]:
    """Cross-entropy to the projected n-step distributional target (``bootstrap_gamma`` is
    gamma^n: the batch's reward is already the n-step sum)."""
    values = bootstrap_values(reward, discount, bootstrap_gamma, atoms.expand(reward.shape[0], -1))
    target = categorical_projection(values, torch.softmax(target_logits, -1), atoms).detach()
    loss = categorical_cross_entropy(logits, target).mean()
    q = (torch.softmax(logits, -1) * atoms).sum(-1).mean()
    return loss, {"critic/loss": loss, "critic/q_mean": q}


def policy_loss(
    q_logits: torch.Tensor,
    atoms: torch.Tensor,
    action: torch.Tensor | None = None,
    dqda_clip_norm: float = 0.0,
) -> tuple[torch.Tensor, common.Metrics]:
    """Deterministic policy gradient through the critic's mean Q = E[Z(s, pi(s))]: the loss's
    gradient is -E[dQ/da da/dw]. With ``dqda_clip_norm`` > 0 each example's dQ/da (taken at
    ``action``, the policy's output) is first clipped to that norm, as Acme's ``losses.dpg``
    (loss 0.5 ||stop(a + clip(dQ/da)) - a||^2). ``actor/loss`` reports -E[Q] either way."""
    q = (torch.softmax(q_logits, -1) * atoms).sum(-1)
    if dqda_clip_norm <= 0:
        loss = -q.mean()
        return loss, {"actor/loss": loss}
    if action is None:  # the clipped gradient is taken at the policy's action
        raise RluError("d4pg policy_loss: dqda_clip_norm > 0 needs the action (a bug in rlu)")
    dqda = torch.autograd.grad(q.sum(), action)[0]
    norm = torch.linalg.vector_norm(dqda, dim=-1, keepdim=True)
    clipped = dqda * (dqda_clip_norm / norm.clamp(min=dqda_clip_norm))  # tf.clip_by_norm
    loss = 0.5 * ((action + clipped).detach() - action).pow(2).sum(-1).mean()
    return loss, {"actor/loss": -q.mean().detach(), "actor/dqda_norm": norm.mean()}


class D4PGAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: D4PGConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        if config.init not in ("acme", "torch"):
            raise RluError(f"D4PGConfig.init={config.init!r}; choose 'acme' or 'torch'")
        self.config, self.device, self.step = config, common.device(device), 0
        self.scaler = nets.ActionScaler(action_spec)
        self.batch_spec = BatchSpec(config.batch_size, n_step=config.n_step, gamma=config.gamma)
        self.num_steps, self.pretrain_steps = config.num_steps, 0
        self.generator = common.generator(stream_seed(seed, "learner"), self.device)
        a, d = self.scaler.dim, self.device
        with common.seeded(seed):
            self.policy = Policy(observation_spec, a, config).to(d)
            self.critic = Critic(observation_spec, a, config).to(d)
        built = common.actor_critic(self.policy, self.critic, config.policy_lr, config.critic_lr)
        self.target_policy, self.target_critic = built.target_actor, built.target_critic
        self.modules, self.optimizers = built.modules, built.optimizers
        self.generators = {"sample": self.generator}
        # copied into their targets every target_update_period updates
        self.targets = built.targets

    def update(self, batch: Transition) -> dict[str, float]:
        c, b = self.config, common.transition(batch, self.scaler, self.device)
        atoms = self.critic.head.atoms
        with torch.no_grad():
            next_a = self.target_policy(b.next_observation)
            target_logits = self.target_critic(b.next_observation, next_a)
        loss_c, metrics = critic_loss(
            self.critic(b.observation, b.action), target_logits, b.reward, b.discount, atoms,
            self.batch_spec.bootstrap_gamma,
        )  # fmt: skip
        # Acme's learner: the policy at the next observations, through the critic as it was
        # before this update's critic step (so the policy steps first: the critic's step would
        # change weights the policy's backward pass still reads)
        pi_a = self.policy(b.next_observation)
        loss_p, m = policy_loss(self.critic(b.next_observation, pi_a), atoms, pi_a,
                                c.dqda_clip_norm)  # fmt: skip
        metrics.update(m)
        common.sgd_step(self.optimizers["policy"], loss_p, list(self.policy.parameters()),
                        c.max_grad_norm)  # fmt: skip
        common.sgd_step(self.optimizers["critic"], loss_c, max_norm=c.max_grad_norm)
        self.step = common.advance(self.step, c.target_update_period, self.targets)
        return common.metrics_to_floats(metrics)

    @torch.inference_mode()
    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """pi(s), greedy or not: the policy is deterministic and, offline, acts without the
        online agent's exploration noise."""
        return self.scaler.from_unit(self.policy(common.to_torch(observation, self.device)))

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = D4PGAgent
