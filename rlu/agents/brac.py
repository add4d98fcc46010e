"""BRAC with value penalty (Wu, Tucker and Nachum 2019; paper appendix A.1, "BRAC").

As in the original (github.com/google-research/google-research, ``behavior_regularized_offline_rl``,
``brac_primal_agent``): a tanh-Gaussian policy (200-200), two critics (300-300) whose target is
the min of the target critics (hard copies every 100 updates, the paper's table for every
continuous agent; the original's Polyak tau = 0.005 is ``target_update_period=0``), and the
value penalty: the KL from the policy to a behaviour model is subtracted from the next-state
value in the critic target and added to the actor loss,

    y = r + gamma d (min_i Q'_i(s', a') - alpha KL(s')),  a' ~ pi(s')
    L_pi = E_s [alpha KL(s) - min_i Q_i(s, a)],            a  ~ pi(s)

with KL(s) = mean over ``num_kl_samples`` a ~ pi(s) of log pi(a|s) - log b(a|s). The behaviour
model b is a tanh-Gaussian (200-200) trained by behaviour cloning separately, first: the first
``behaviour_steps`` updates (300 000 in the paper, Adam 5e-4) train only b, later updates train
critics and policy against the frozen b. That phase is the agent's ``pretrain_steps``: the
training loop runs it on top of the ``num_steps`` learner steps. Critic Adam 1e-3, batch 256;
the paper sweeps the policy learning rate over {1e-5, 1e-4, 3e-5} and alpha over
{0.1, 0.3, 1.0} (``GRID``); the ``paper`` preset takes 3e-5 and 0.1 from those grids.

Deviations: actions are clipped to +-(1 - 1e-3) before b's log density (as the original's
``clip_eps``); no SAC entropy term in the actor (the KL's log pi term already keeps the policy's
spread). ``act(greedy=True)`` returns tanh(mean).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from rlu.agents import common
from rlu.agents import networks as nets
from rlu.agents.losses import sample_kl, tanh_gaussian_log_prob
from rlu.types import BatchSpec, Transition


@dataclass(frozen=True)
class BRACConfig:
    policy_layers: tuple[int, ...] = (200, 200)
    """Policy hidden sizes."""
    critic_layers: tuple[int, ...] = (300, 300)
    """Hidden sizes of each critic."""
    behaviour_layers: tuple[int, ...] = (200, 200)
    """Behaviour model hidden sizes."""
    torso_hidden: int = 64
    """Camera ResNet embedding size."""
    alpha: float = 0.1
    """Weight of the KL value penalty (grid {0.1, 0.3, 1.0})."""
    num_kl_samples: int = 4
    """Policy samples per state in the KL estimate."""
    gamma: float = 0.99
    """Discount."""
    target_update_period: int = 100
    """Updates between hard copies into the target critics (the paper's table, shared by its
    continuous agents); 0: Polyak averaging with ``tau`` every update (the original BRAC)."""
    tau: float = 0.005
    """Polyak rate of the target critics when ``target_update_period`` is 0."""
    policy_lr: float = 3e-5
    """Adam learning rate of the policy (grid {1e-5, 1e-4, 3e-5})."""
    critic_lr: float = 1e-3
    """Adam learning rate of the critics."""
    behaviour_lr: float = 5e-4
    """Adam learning rate of the behaviour model."""
    behaviour_steps: int = 300_000
    """Updates spent training only the behaviour model before the agent trains (pre-training,
    run by the loop on top of ``num_steps``)."""
    batch_size: int = 256
    """Transitions per update."""
    num_steps: int = 1_000_000
    """Learner steps of a full run: what ``rlu train`` runs when no --steps is given. The paper
    states no budget for the continuous baselines; 1M is rlu's choice."""


Config = BRACConfig
PRESETS = {
    "paper": BRACConfig(),
    "small": BRACConfig(policy_layers=(256, 256), critic_layers=(256, 256),
                        behaviour_layers=(256, 256), policy_lr=3e-4, alpha=0.3,
                        behaviour_steps=2_000, num_steps=20_000, target_update_period=0),
}  # fmt: skip
GRID: dict[str, list] = {"policy_lr": [1e-5, 1e-4, 3e-5], "alpha": [0.1, 0.3, 1.0]}

CLIP = 1.0 - 1e-3


class TanhGaussian(nn.Module):
    def __init__(self, observation_spec, action_dim: int, layers, torso_hidden: int):
        super().__init__()
        self.encoder = nets.Encoder(observation_spec, torso_hidden)
        self.net = nets.mlp(self.encoder.output_dim, layers, 2 * action_dim)

    def forward(self, obs):
        return self.dist(self.encoder(obs))

    def dist(self, features: torch.Tensor):
        mean, log_std = self.net(features).chunk(2, -1)
        return mean, log_std.clamp(-5.0, 2.0).exp()

    def log_prob(self, obs, action, features=None):
        """log b(action | s); ``action`` (B, A) or (S, B, A) against (B, ...) states."""
        f = self.encoder(obs) if features is None else features
        mean, std = self.dist(f)
        u = torch.atanh(action.clamp(-CLIP, CLIP))
        return tanh_gaussian_log_prob(mean, std, u)

    def sample(self, obs, num: int, generator: torch.Generator):
        """(num, B, A) actions and their log densities (reparameterised)."""
        mean, std = self(obs)
        u = mean + std * torch.randn((num, *mean.shape), generator=generator, device=mean.device)
        return torch.tanh(u), tanh_gaussian_log_prob(mean, std, u)


class Critics(nn.Module):
    def __init__(self, observation_spec, action_dim: int, layers, torso_hidden: int):
        super().__init__()
        self.encoder = nets.Encoder(observation_spec, torso_hidden)
        f = self.encoder.output_dim + action_dim
        self.q1, self.q2 = nets.mlp(f, layers, 1), nets.mlp(f, layers, 1)

    def forward(self, obs, action: torch.Tensor) -> torch.Tensor:
        """Q of (B, ...) states and (S, B, A) or (B, A) actions: the min of the two critics."""
        s = self.encoder(obs)
        s = s.expand(*action.shape[:-1], s.shape[-1])
        sa = torch.cat([s, action], -1)
        return torch.stack([self.q1(sa).squeeze(-1), self.q2(sa).squeeze(-1)])


def behaviour_loss(log_prob):
    loss = -log_prob.mean()
    return loss, {"behaviour/loss": loss}


def critic_loss(q, target):
    """q: (2, B) critics' values; target (B,)."""
    loss = (q - target).pow(2).mean(1).sum()
    return loss, {"critic/loss": loss, "critic/q_mean": q.mean()}


def actor_loss(q_min, kl, alpha: float):
    """Value penalty actor loss: alpha KL(s) - Q(s, a), a ~ pi."""
    loss = (alpha * kl - q_min).mean()
    return loss, {"actor/loss": loss, "actor/kl": kl.mean()}


class BRACAgent:
    def __init__(
        self, observation_spec, action_spec, config: BRACConfig, seed: int = 0, device="cpu"
    ):
        self.config, self.device = config, common.device(device)
        self.scaler = nets.ActionScaler(action_spec)
        self.batch_spec = BatchSpec(config.batch_size, gamma=config.gamma)
        self.pretrain_steps = config.behaviour_steps
        self.num_steps = config.num_steps
        self.generator = common.generator(seed, self.device)
        a, th, d = self.scaler.dim, config.torso_hidden, self.device
        with common.seeded(seed):
            self.policy = TanhGaussian(observation_spec, a, config.policy_layers, th).to(d)
            self.behaviour = TanhGaussian(observation_spec, a, config.behaviour_layers, th).to(d)
            self.critics = Critics(observation_spec, a, config.critic_layers, th).to(d)
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
        self.step = 0

    def _kl(self, obs, samples, log_pi):
        """KL(pi || b)(s) from (S, B, A) samples a ~ pi and their log pi (b is frozen here)."""
        return sample_kl(log_pi, self.behaviour.log_prob(obs, samples))

    def update(self, batch: Transition) -> dict[str, float]:
        c, g, d = self.config, self.generator, self.device
        obs = common.to_torch(batch.observation, d)
        action = self.scaler.to_unit(common.to_torch(batch.action, d))
        if self.step < c.behaviour_steps:
            loss, metrics = behaviour_loss(self.behaviour.log_prob(obs, action))
            common.sgd_step(self.optimizers["behaviour"], loss)
            self.step += 1
            return common.metrics_to_floats(metrics)

        next_obs = common.to_torch(batch.next_observation, d)
        reward, discount = common.to_torch(batch.reward, d), common.to_torch(batch.discount, d)
        with torch.no_grad():
            next_a, next_logp = self.policy.sample(next_obs, c.num_kl_samples, g)
            kl_next = self._kl(next_obs, next_a, next_logp)
            q_next = self.target_critics(next_obs, next_a[0]).amin(0)
            target = reward + c.gamma * discount * (q_next - c.alpha * kl_next)
        loss_c, metrics = critic_loss(self.critics(obs, action), target)
        common.sgd_step(self.optimizers["critic"], loss_c)

        samples, logp = self.policy.sample(obs, c.num_kl_samples, g)
        kl = self._kl(obs, samples, logp)
        q = self.critics(obs, samples[0]).amin(0)
        loss_a, m = actor_loss(q, kl, c.alpha)
        metrics.update(m)
        common.sgd_step(self.optimizers["policy"], loss_a, inputs=list(self.policy.parameters()))

        self.step += 1
        if c.target_update_period > 0:
            targets = {self.target_critics: self.critics}
            common.periodic_update(self.step, c.target_update_period, targets)
        else:
            common.soft_update(self.target_critics, self.critics, c.tau)
        return common.metrics_to_floats(metrics)

    @torch.inference_mode()
    def act(self, observation, greedy: bool = True, is_first=None) -> np.ndarray:
        obs = common.to_torch(observation, self.device)
        if greedy:
            return self.scaler.from_unit(torch.tanh(self.policy(obs)[0]))
        return self.scaler.from_unit(self.policy.sample(obs, 1, self.generator)[0][0])

    state_dict = common.state_dict
    load_state_dict = common.load_state_dict


Agent = BRACAgent
