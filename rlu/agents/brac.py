"""BRAC with value penalty (Wu, Tucker and Nachum 2019; paper appendix A.1, "BRAC").

As in the original (github.com/google-research/google-research, ``behavior_regularized_offline_rl``,
``brac_primal_agent``): a tanh-Gaussian policy (200-200), two critics (300-300) whose target is
the min of the target critics (hard copies every 100 updates, the paper's table for every
continuous agent; the original's Polyak tau = 0.005 is ``target_update_period=0``), and the
value penalty: the KL from the policy to a behaviour model is subtracted from the next-state
value in the critic target and added to the actor loss,

    y = r + gamma d (min_i Q'_i(s', a') - alpha KL(s')),  a' ~ pi(s')
    L_pi = E_s [alpha KL(s) - w_k min_i Q_i(s, a)],        a  ~ pi(s)

with KL(s) = mean over ``num_kl_samples`` a ~ pi(s) of log pi(a|s) - log b(a|s), and the
original's warm start: w_k = 0 for the first ``warm_start_steps`` agent updates k (20 000, the
original's ``warm_start``: ``q_start = global_step > warm_start``), so the policy first moves
towards b under the KL alone while the critics learn, then w_k = 1. The policy and b are the
original's ``ActorNetwork``: tanh(u), u ~ N(mean, std) with log std = -5 + 2.5 (tanh(raw) + 1)
in [-5, 0] (``networks.TanhGaussianPolicy`` with ``squash_log_std``). The behaviour
model b is a tanh-Gaussian (200-200) trained by behaviour cloning separately, first: the first
``behaviour_steps`` updates (300 000 in the paper, Adam 5e-4) train only b, later updates train
critics and policy against the frozen b. That phase is the agent's ``pretrain_steps``: the
training loop runs it on top of the ``num_steps`` learner steps. Critic Adam 1e-3, batch 256;
the paper sweeps the policy learning rate over {1e-5, 1e-4, 3e-5} and alpha over
{0.1, 0.3, 1.0} (``GRID``); the ``paper`` preset takes 3e-5 and 0.1 from those grids.

As the original's defaults (``alpha_entropy=0``): no SAC entropy term in the actor (the KL's
log pi term already keeps the policy's spread); actions are clipped to +-(1 - 1e-3) before b's
log density (the original's ``clip_eps``). The warm start counts agent updates from 0 and turns
the Q term on at k = ``warm_start_steps``, one update before the original's ``>`` does (so that
0 means no warm start). ``act(greedy=True)`` returns tanh(mean).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from rlu.agents import common
from rlu.agents import networks as nets
from rlu.agents.losses import sample_kl
from rlu.files import (
    BATCH,
    FRACTION,
    LAYERS,
    LEARNING_RATE,
    MAX_STEPS,
    STEPS,
    WIDTH,
    Checked,
    bounds,
)
from rlu.seeds import stream_seed
from rlu.types import ActionSpec, BatchSpec, Observation, ObservationSpec, Transition


@dataclass(frozen=True)
class BRACConfig(Checked):
    policy_layers: tuple[int, ...] = field(default=(200, 200), metadata=LAYERS)
    """Policy hidden sizes."""
    critic_layers: tuple[int, ...] = field(default=(300, 300), metadata=LAYERS)
    """Hidden sizes of each critic."""
    behaviour_layers: tuple[int, ...] = field(default=(200, 200), metadata=LAYERS)
    """Behaviour model hidden sizes."""
    torso_hidden: int = field(default=64, metadata=WIDTH)
    """Camera ResNet embedding size."""
    alpha: float = field(default=0.1, metadata=bounds(min=0.0, max=1e6))
    """Weight of the KL value penalty (grid {0.1, 0.3, 1.0})."""
    num_kl_samples: int = field(default=4, metadata=bounds(min=1, max=10_000))
    """Policy samples per state in the KL estimate."""
    gamma: float = field(default=0.99, metadata=FRACTION)
    """Discount."""
    target_update_period: int = field(default=100, metadata=bounds(min=0, max=MAX_STEPS))
    """Updates between hard copies into the target critics (the paper's table, shared by its
    continuous agents); 0: Polyak averaging with ``tau`` every update (the original BRAC)."""
    tau: float = field(default=0.005, metadata=bounds(gt=0.0, max=1.0))
    """Polyak rate of the target critics when ``target_update_period`` is 0."""
    policy_lr: float = field(default=3e-5, metadata=LEARNING_RATE)
    """Adam learning rate of the policy (grid {1e-5, 1e-4, 3e-5})."""
    critic_lr: float = field(default=1e-3, metadata=LEARNING_RATE)
    """Adam learning rate of the critics."""
    behaviour_lr: float = field(default=5e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the behaviour model."""
    behaviour_steps: int = field(default=300_000, metadata=bounds(min=0, max=MAX_STEPS))
    """Updates spent training only the behaviour model before the agent trains (pre-training,
    run by the loop on top of ``num_steps``)."""
    warm_start_steps: int = field(default=20_000, metadata=bounds(min=0, max=MAX_STEPS))
    """Agent updates, after the behaviour phase, whose policy loss has no Q term, only the KL
    penalty (the original's ``warm_start=20000``); 0: none."""
    batch_size: int = field(default=256, metadata=BATCH)
    """Transitions per update."""
    num_steps: int = field(default=1_000_000, metadata=STEPS)
    """Learner steps of a full run: what ``rlu train`` runs when no --steps is given. The paper
    states no budget for the continuous baselines; 1M is rlu's choice."""


Config = BRACConfig
PRESETS = {
    "paper": BRACConfig(),
    # warm start: 4 % of the run, as the original's 20k of its 500k (run_primal.sh)
    "small": BRACConfig(policy_layers=(256, 256), critic_layers=(256, 256),
                        behaviour_layers=(256, 256), policy_lr=3e-4, alpha=0.3,
                        behaviour_steps=2_000, warm_start_steps=800, num_steps=20_000,
                        target_update_period=0),
}  # fmt: skip
GRID: dict[str, list] = {"policy_lr": [1e-5, 1e-4, 3e-5], "alpha": [0.1, 0.3, 1.0]}

CLIP = 1.0 - 1e-3
LOG_STD_RANGE = (-5.0, 0.0)  # the original's LOG_STD_MIN, LOG_STD_MAX (networks.py)


def behaviour_loss(log_prob: torch.Tensor) -> tuple[torch.Tensor, common.Metrics]:
    loss = -log_prob.mean()
    return loss, {"behaviour/loss": loss}


def critic_loss(q: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, common.Metrics]:
    """q: (2, B) critics' values; target (B,)."""
    loss = (q - target).pow(2).mean(1).sum()
    return loss, {"critic/loss": loss, "critic/q_mean": q.mean()}


def actor_loss(
    q_min: torch.Tensor, kl: torch.Tensor, alpha: float
) -> tuple[torch.Tensor, common.Metrics]:
    """Value penalty actor loss: alpha KL(s) - Q(s, a), a ~ pi (``q_min`` 0 in the warm start)."""
    loss = (alpha * kl - q_min).mean()
    return loss, {"actor/loss": loss, "actor/kl": kl.mean()}


class BRACAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: BRACConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.scaler = nets.ActionScaler(action_spec)
        self.batch_spec = BatchSpec(config.batch_size, gamma=config.gamma)
        self.num_steps, self.pretrain_steps = config.num_steps, config.behaviour_steps
        self.generator = common.generator(stream_seed(seed, "learner"), self.device)
        a, th, d = self.scaler.dim, config.torso_hidden, self.device
        with common.seeded(seed):
            self.policy = nets.TanhGaussianPolicy(
                observation_spec, a, config.policy_layers, th, LOG_STD_RANGE, squash_log_std=True
            ).to(d)
            self.behaviour = nets.TanhGaussianPolicy(
                observation_spec, a, config.behaviour_layers, th, LOG_STD_RANGE, squash_log_std=True
            ).to(d)
            self.critics = nets.TwinCritic(observation_spec, a, config.critic_layers, th).to(d)
        self.target_critics = common.frozen_copy(self.critics)
        self.optimizers = {
            "policy": common.adam(self.policy.parameters(), config.policy_lr),
            "behaviour": common.adam(self.behaviour.parameters(), config.behaviour_lr),
            "critic": common.adam(self.critics.parameters(), config.critic_lr),
        }
        self.generators = {"sample": self.generator}
        self.modules = {
            "policy": self.policy, "behaviour": self.behaviour,
            "critics": self.critics, "target_critics": self.target_critics,
        }  # fmt: skip

    def _kl(
        self, obs: common.TensorObservation, samples: torch.Tensor, log_pi: torch.Tensor
    ) -> torch.Tensor:
        """KL(pi || b)(s) from (S, B, A) samples a ~ pi and their log pi (b is frozen here)."""
        return sample_kl(log_pi, self.behaviour.log_prob(obs, samples, CLIP))

    def update(self, batch: Transition) -> dict[str, float]:
        c, g, d = self.config, self.generator, self.device
        if self.step < c.behaviour_steps:
            obs = common.to_torch(batch.observation, d)
            action = self.scaler.to_unit(common.to_torch(batch.action, d))
            loss, metrics = behaviour_loss(self.behaviour.log_prob(obs, action, CLIP))
            common.sgd_step(self.optimizers["behaviour"], loss)
            self.step += 1
            return common.metrics_to_floats(metrics)

        b = common.transition(batch, self.scaler, d)
        obs, next_obs = b.observation, b.next_observation
        with torch.no_grad():
            next_a, next_logp = self.policy.sample(next_obs, c.num_kl_samples, g)
            kl_next = self._kl(next_obs, next_a, next_logp)
            q_next = self.target_critics(next_obs, next_a[0]).amin(0)
            target = b.reward + c.gamma * b.discount * (q_next - c.alpha * kl_next)
        loss_c, metrics = critic_loss(self.critics(obs, b.action), target)
        common.sgd_step(self.optimizers["critic"], loss_c)

        samples, logp = self.policy.sample(obs, c.num_kl_samples, g)
        kl = self._kl(obs, samples, logp)
        if self.step - c.behaviour_steps >= c.warm_start_steps:
            q = self.critics(obs, samples[0]).amin(0)
        else:  # the warm start: the KL penalty alone
            q = torch.zeros_like(kl)
        loss_a, m = actor_loss(q, kl, c.alpha)
        metrics.update(m)
        common.sgd_step(self.optimizers["policy"], loss_a, inputs=list(self.policy.parameters()))

        targets = {self.target_critics: self.critics}
        self.step = common.advance(self.step, c.target_update_period, targets, c.tau)
        return common.metrics_to_floats(metrics)

    @torch.inference_mode()
    def act(
        self,
        observation: Observation,
        greedy: bool = True,
        is_first: np.ndarray | None = None,
        reward: np.ndarray | None = None,
    ) -> np.ndarray:
        """tanh(mean) of the tanh-Gaussian policy with ``greedy=True`` (the original's
        ``DeterministicSoftPolicy``); with ``greedy=False`` one of its samples."""
        obs = common.to_torch(observation, self.device)
        if greedy:
            return self.scaler.from_unit(torch.tanh(self.policy(obs)[0]))
        return self.scaler.from_unit(self.policy.sample(obs, 1, self.generator)[0][0])

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)


Agent = BRACAgent
