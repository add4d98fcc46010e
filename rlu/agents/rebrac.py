"""ReBRAC (Tarasov, Kurenkov, Nikulin and Kolesnikov 2023, "Revisiting the Minimalist Approach
to Offline Reinforcement Learning", NeurIPS 2023).

TD3+BC with the design choices of later offline RL work added back: the behaviour-cloning
penalty decoupled into one for the actor (beta_1) and one inside the critic's target (beta_2,
BRAC's value penalty), LayerNorm in the critics, deeper networks (3 x 256), a larger batch
(1024) and learning rates 1e-3:

    a'     =  clip(pi'(s') + clip(sigma eps, -c, c), -1, 1),    eps ~ N(0, I)
    y      =  r + gamma d (min_j Q'_j(s', a') - beta_2 ||a' - a'_D||^2)
    L_Q    =  sum_i E[(Q_i(s, a) - y)^2]
    L_pi   =  E[beta_1 ||pi(s) - a||^2 - lambda min_j Q_j(s, pi(s))]
    lambda =  1 / E|min_j Q_j(s, pi(s))|

with a'_D the data's next action, ||.||^2 summed over the action's dimensions and lambda held
fixed (``normalize_q``; lambda = 1 without it). Original code: github.com/tinkoff-ai/ReBRAC
(``src/algorithms/rebrac.py``: update; ``src/networks.py``: ``DetActor``, ``EnsembleCritic``;
``src/nn.py``: initialisation; ``configs/rebrac/*``: the per-dataset settings); CORL's
``algorithms/offline/rebrac.py`` (github.com/tinkoff-ai/CORL) is the same code.

The ``paper`` preset is the paper's and the original's D4RL Gym-MuJoCo setting: actor 3 x 256
ReLU without LayerNorm (tanh output), two critics 3 x 256 ReLU each followed by a LayerNorm,
Adam 1e-3 for both, batch 1024, discount 0.99, Polyak rate 0.005, target noise 0.2 clipped to
0.5, actor and targets every second update, Q normalisation on, 1M updates (1000 epochs of
1000), no observation normalisation. The penalty weights are tuned per dataset in the paper; the
preset takes beta_1 = beta_2 = 0.01, the pair the paper chose most often on Gym-MuJoCo (5 of its
18 datasets). The original ``Config``'s defaults (1.0 and 1.0) are placeholders that no dataset
config keeps; on the bundled cartpole data they held the return near 200 where 0.01 and 0.01
climbed past the data's (docs/agents.md, "Learning on the bundled data"). ``GRID`` is the
paper's Gym-MuJoCo sweep (the original's ``configs/sweeps/tuning/rebrac_locomotion_sweep.yaml``):
beta_1 in {0.001, 0.01, 0.05, 0.1}, beta_2 in {0, 0.001, 0.01, 0.1, 0.5}; the values it chose per
dataset are in docs/paper_settings.md. Initialisation as the original's ("as in the EDAC
paper"): hidden layers torch's default weights (uniform +-1/sqrt(fan_in)) with biases 0.1, the
output layer's weights and biases uniform in +-1e-3 (actor) and +-3e-3 (critics).

Observations: the original normalises none (``normalize_states: False`` in its ``Config`` and in
every dataset config); ``normalize_observations=True`` does it as TD3+BC does, through the
loop's dataset statistics (``batch_spec.statistics``, :meth:`ReBRACAgent.set_statistics`, kept in
the agent's state).

As the original, the actor learns from the freshly updated critics, the target actor moves
towards the actor as it was before its step (``optax.incremental_update(actor.params, ...)`` on
the pre-step parameters) and the target critics towards the updated critics.

Deviations and choices:
- The actor and the targets learn on updates 2, 4, 6, ... where the original's ``arange(n) %
  policy_freq == 0`` steps them on its updates 1, 3, 5, ...: one update later, so that the
  loop's logged steps (multiples of an even period) carry the ``actor/*`` metrics, which only
  actor updates report.
- A transition whose next observation ends its episode has no next action in the data (RLDS:
  the final step's action means nothing; rlu stores zeros), so beta_2's penalty there compares
  a' with zeros. D4RL's ``qlearning_dataset`` drops time-out transitions, so the original never
  meets one; in 1000-step control-suite episodes it is one transition in 1000, and after a
  terminal step the penalty is multiplied by d = 0.
- Observations go through ``networks.Encoder`` (cameras through the ResNet torso, with torch's
  initialisation); the twin critics share one encoder (``networks.TwinCritic``).
- Actions are learned in [-1, 1] (``networks.ActionScaler``), as the original's D4RL tasks.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents import networks as nets
from rlu.agents.losses import smoothed_target_action
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
from rlu.types import (
    ActionSpec,
    BatchSpec,
    DataStatistics,
    Observation,
    ObservationSpec,
    Transition,
)


@dataclass(frozen=True)
class ReBRACConfig(Checked):
    """In the order of the original's ``Config`` (its names in the field docstrings)."""

    actor_lr: float = field(default=1e-3, metadata=LEARNING_RATE)
    """``actor_learning_rate``: Adam's rate for the actor (Gym-MuJoCo; 3e-4 elsewhere)."""
    critic_lr: float = field(default=1e-3, metadata=LEARNING_RATE)
    """``critic_learning_rate``: Adam's rate for the critics (Gym-MuJoCo; 3e-4 Adroit, 5e-5
    AntMaze)."""
    actor_layers: tuple[int, ...] = field(
        default=(256, 256, 256),
        metadata=LAYERS,
    )
    """``hidden_dim`` x ``actor_n_hiddens``: the actor's hidden sizes (ReLU, tanh output)."""
    critic_layers: tuple[int, ...] = field(
        default=(256, 256, 256),
        metadata=LAYERS,
    )
    """``hidden_dim`` x ``critic_n_hiddens``: each critic's hidden sizes (ReLU)."""
    torso_hidden: int = field(default=64, metadata=WIDTH)
    """Camera ResNet embedding size (rlu's; the original has feature observations only)."""
    gamma: float = field(default=0.99, metadata=FRACTION)
    """``gamma``: the discount (the paper's AntMaze runs use 0.999)."""
    tau: float = field(default=0.005, metadata=bounds(gt=0.0, max=1.0))
    """``tau``: Polyak rate of the target actor and critics, on the actor's updates."""
    actor_bc_coef: float = field(default=0.01, metadata=bounds(min=0.0, max=1e6))
    """``actor_bc_coef``, beta_1: weight of the actor's ||pi(s) - a||^2 (tuned per dataset; the
    paper's most frequent Gym-MuJoCo pick; the original's default 1.0)."""
    critic_bc_coef: float = field(default=0.01, metadata=bounds(min=0.0, max=1e6))
    """``critic_bc_coef``, beta_2: weight of the target's ||a' - a'_D||^2 (tuned per dataset;
    the paper's most frequent Gym-MuJoCo pick; the original's default 1.0)."""
    actor_layer_norm: bool = False
    """``actor_ln``: a LayerNorm after every hidden ReLU of the actor."""
    critic_layer_norm: bool = True
    """``critic_ln``: a LayerNorm after every hidden ReLU of the critics."""
    policy_noise: float = field(default=0.2, metadata=bounds(min=0.0, max=1e3))
    """``policy_noise``: std of the noise on the target actor's actions (in [-1, 1])."""
    noise_clip: float = field(default=0.5, metadata=bounds(min=0.0, max=1e3))
    """``noise_clip``: that noise is clipped to +-noise_clip."""
    policy_freq: int = field(default=2, metadata=bounds(min=1, max=1000))
    """``policy_freq``: the actor and the targets learn on every policy_freq-th update."""
    normalize_q: bool = True
    """``normalize_q``: scale the actor's Q term by 1 / E|Q|, held fixed (TD3+BC's lambda)."""
    batch_size: int = field(default=1024, metadata=BATCH)
    """``batch_size``: transitions per update (Gym-MuJoCo; 256 in the paper's other domains)."""
    num_steps: int = field(default=1_000_000, metadata=STEPS)
    """``num_epochs`` x ``num_updates_on_epoch`` (1000 x 1000): learner steps of a full run."""
    normalize_observations: bool = False
    """``normalize_states``: standardise observations, (s - mean) / (std + 1e-3), with the
    dataset's per-feature mean and std (off in all the original's runs)."""


Config = ReBRACConfig
PRESETS = {
    "paper": ReBRACConfig(),
    # CPU minutes: the paper's depth, TD3+BC's batch (the paper's non-MuJoCo batch)
    "small": ReBRACConfig(batch_size=256, num_steps=20_000),
}
GRID = {  # the paper's Gym-MuJoCo sweep (docstring); per-dataset picks: docs/paper_settings.md
    "actor_bc_coef": [0.001, 0.01, 0.05, 0.1],
    "critic_bc_coef": [0.0, 0.001, 0.01, 0.1, 0.5],
}


def edac_init(net: nn.Sequential, last_bound: float) -> nn.Sequential:
    """The original's initialisation of an MLP: hidden biases 0.1 (weights keep torch's default,
    the original's ``pytorch_init``), the output layer's weights and biases uniform in
    +-``last_bound``. Draws from torch's global RNG: call it under ``common.seeded``."""
    linears = [m for m in net if isinstance(m, nn.Linear)]
    with torch.no_grad():
        for layer in linears[:-1]:
            layer.bias.fill_(0.1)
        linears[-1].weight.uniform_(-last_bound, last_bound)
        linears[-1].bias.uniform_(-last_bound, last_bound)
    return net


def build_networks(
    observation_spec: ObservationSpec, action_dim: int, c: ReBRACConfig
) -> tuple[nets.DeterministicPolicy, nets.TwinCritic]:
    """The actor and the twin critics, initialised as the original's (``edac_init``)."""
    actor = nets.DeterministicPolicy(
        observation_spec, action_dim, c.actor_layers, c.torso_hidden, c.actor_layer_norm
    )
    critics = nets.TwinCritic(
        observation_spec, action_dim, c.critic_layers, c.torso_hidden, c.critic_layer_norm
    )
    edac_init(actor.net, 1e-3)
    edac_init(critics.q1, 3e-3)
    edac_init(critics.q2, 3e-3)
    return actor, critics


def critic_target(
    reward: torch.Tensor,
    discount: torch.Tensor,
    bootstrap_gamma: float,
    next_q: torch.Tensor,
    next_action: torch.Tensor,
    data_action: torch.Tensor,
    beta: float,
) -> tuple[torch.Tensor, common.Metrics]:
    """r + gamma^n d (min_j Q'_j(s', a') - beta ||a' - a'_D||^2): target critics' (2, B) values,
    the smoothed next actions and the data's (B, A). Returns the target and its metrics."""
    penalty = (next_action - data_action).pow(2).sum(-1)
    target = reward + bootstrap_gamma * discount * (next_q.amin(0) - beta * penalty)
    return target, {"critic/bc_penalty": penalty.mean()}


def critic_loss(q: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, common.Metrics]:
    """Sum over the twin critics (2, B) of the mean squared error to the fixed target (B,)."""
    loss = (q - target.detach()).pow(2).mean(1).sum()
    return loss, {"critic/loss": loss, "critic/q_min": q.amin(0).mean()}


def actor_loss(
    q: torch.Tensor,
    policy_action: torch.Tensor,
    action: torch.Tensor,
    beta: float,
    normalize_q: bool,
) -> tuple[torch.Tensor, common.Metrics]:
    """mean(beta ||pi(s) - a||^2 - lambda min_j Q_j(s, pi(s))), lambda = 1 / mean |min_j Q_j|
    held fixed (1 without ``normalize_q``); ``q`` (B,) is the critics' min at the policy's
    actions (B, A), ``action`` the data's."""
    bc = (policy_action - action).pow(2).sum(-1)
    lmbda = 1.0 / q.abs().mean().detach() if normalize_q else torch.ones_like(q[0])
    loss = (beta * bc - lmbda * q).mean()
    return loss, {"actor/loss": loss, "actor/bc_loss": bc.mean(), "actor/lambda": lmbda,
                  "actor/q_mean": q.mean()}  # fmt: skip


class ReBRACAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: ReBRACConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.scaler = nets.ActionScaler(action_spec)
        normalize = config.normalize_observations  # the original's compute_mean_std(eps=1e-3)
        self.normaliser = nets.ObservationNormaliser(observation_spec, 1e-3, normalize)
        self.normaliser.to(self.device)
        self.batch_spec = BatchSpec(
            config.batch_size, gamma=config.gamma, statistics=self.normaliser.statistics
        )
        self.num_steps, self.pretrain_steps = config.num_steps, 0
        self.generator = common.generator(stream_seed(seed, "learner"), self.device)
        with common.seeded(seed):
            actor, critics = build_networks(observation_spec, self.scaler.dim, config)
        self.actor, self.critics = actor.to(self.device), critics.to(self.device)
        built = common.actor_critic(
            self.actor, self.critics, config.actor_lr, config.critic_lr, ("actor", "critics"),
            {"normaliser": self.normaliser},
        )  # fmt: skip
        self.target_actor, self.target_critics = built.target_actor, built.target_critic
        self.actor_params = list(self.actor.parameters())
        self.modules, self.optimizers = built.modules, built.optimizers
        self.generators = {"noise": self.generator}

    def set_statistics(self, stats: DataStatistics) -> None:
        """Take the dataset's observation mean and std (used with ``normalize_observations``;
        the loop computes them once, before the first update); kept in the agent's state."""
        self.normaliser.set(stats)

    def update(self, batch: Transition) -> dict[str, float]:
        self.normaliser.require("rebrac")
        c = self.config
        b = common.transition(batch, self.scaler, self.device)
        data_next_action = self.scaler.to_unit(common.to_torch(batch.next_action, self.device))
        # every network here encodes the same spec: the keys are joined once per batch
        flat, norm = self.critics.encoder.flatten, self.normaliser
        obs, next_obs = flat(norm(b.observation)), flat(norm(b.next_observation))

        with torch.no_grad():
            next_action = smoothed_target_action(
                self.target_actor(next_obs), c.policy_noise, c.noise_clip, self.generator
            )
            target, metrics = critic_target(
                b.reward, b.discount, self.batch_spec.bootstrap_gamma,
                self.target_critics(next_obs, next_action), next_action, data_next_action,
                c.critic_bc_coef,
            )  # fmt: skip
        loss_q, m = critic_loss(self.critics(obs, b.action), target)
        metrics.update(m)
        common.sgd_step(self.optimizers["critic"], loss_q)

        actor_step = (self.step + 1) % c.policy_freq == 0
        if actor_step:
            policy_action = self.actor(obs)
            q = self.critics(obs, policy_action).amin(0)
            loss_a, m = actor_loss(q, policy_action, b.action, c.actor_bc_coef, c.normalize_q)
            metrics.update(m)
            common.soft_update(self.target_actor, self.actor, c.tau)  # the pre-step actor
            common.sgd_step(self.optimizers["actor"], loss_a, inputs=self.actor_params)
        targets = {self.target_critics: self.critics}
        self.step = common.advance(self.step, 0, targets, c.tau if actor_step else 0.0)
        return common.metrics_to_floats(metrics)

    @torch.inference_mode()
    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """pi(s), greedy or not: the policy is deterministic and, offline, acts without TD3's
        exploration noise (observations normalised first with ``normalize_observations``)."""
        obs = self.normaliser(common.to_torch(observation, self.device))
        return self.scaler.from_unit(self.actor(obs))

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = ReBRACAgent
