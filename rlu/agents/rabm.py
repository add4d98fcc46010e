"""RABM: distributional, optionally recurrent ABM (Siegel et al. 2020; paper appendix A.1).

ABM ("Keep doing what worked") learns a prior pi_prior by advantage-weighted behaviour cloning,
weights f(A) = 1[A >= 0] with A(s, a) = Q(s, a) - E_{a'~pi} Q(s, a'), then improves the policy
MPO-style (Abdolmaleki et al. 2018) inside a trust region around the prior:

- E-step: N actions a_i ~ pi_prior(s); weights q_i = softmax_i(Q(s, a_i) / eta), with the
  temperature eta trained on the dual g(eta) = eta eps + eta mean_s log mean_i exp(Q / eta);
- M-step: maximise sum_i q_i log pi(a_i | s) under decoupled KL limits (mean eps_mean, std eps_std)
  to the target policy, with Lagrange multipliers trained on their duals.

The "R" of the paper: a categorical distributional critic (21 atoms on [0, 100], table 5) trained
on the policy's own actions with target networks copied every 100 updates, and optional
recurrence (two LSTM-1024 layers after the residual MLP). Prior, policy and critic use BC's
torso (ResNet for cameras, residual MLP 8 x 1024); prior and policy end in one diagonal Gaussian
(MPO's M-step is built for Gaussians). Adam 1e-4 for prior, policy and critic. The paper keeps
"most of the original hyper-parameters" of ABM without listing them; rlu takes Acme's TF MPO
(``acme/agents/tf/mpo``): 20 samples, eps 0.1, eps_std 1e-6, initial log duals 1 (temperature,
alpha_mean) and 10 (alpha_std), duals' Adam 1e-2, and later Acme versions' eps_mean 2.5e-3
(1e-3 in the learner at acme a6d7199).

Deviations: the critic concatenates the action after the observation torso (one torso pass
serves all N sampled actions; with recurrence the LSTM then never sees sampled actions) where
the paper concatenates it before the MLP. Recurrent windows start from a zero state and train
on every real transition t -> t+1 inside the window (1-step targets).

Acting: ``act(greedy=True)`` is the paper's evaluation policy, the Gaussian's mean plus noise of
variance 1e-4 (``eval_variance``, as BC's); ``act(greedy=False)`` samples the learnt Gaussian.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from rlu.agents import common, losses
from rlu.agents import networks as nets
from rlu.files import (
    BATCH,
    FRACTION,
    LEARNING_RATE,
    MAX_LAYERS,
    STEPS,
    WIDTH,
    Checked,
    bounds,
)
from rlu.seeds import stream_seed
from rlu.types import ActionSpec, BatchSpec, Observation, ObservationSpec, Sequence, Transition


@dataclass(frozen=True)
class RABMConfig(Checked):
    hidden_size: int = field(default=1024, metadata=WIDTH)
    """Width of the residual MLPs."""
    num_layers: int = field(default=8, metadata=bounds(min=1, max=MAX_LAYERS))
    """Layers of the residual MLPs."""
    torso_hidden: int = field(default=64, metadata=WIDTH)
    """Camera ResNet embedding size (table 5, ABM & BC column)."""
    recurrent: bool = False
    """Two LSTM layers after each MLP; trains on sequence windows."""
    lstm_hidden: int = field(default=1024, metadata=WIDTH)
    """Hidden size of each LSTM layer."""
    sequence_length: int = field(default=40, metadata=bounds(min=1, max=100_000))
    """Window length of recurrent batches."""
    num_atoms: int = field(default=21, metadata=bounds(min=2, max=10_000))
    """Atoms of the categorical critic."""
    vmin: float = field(default=0.0, metadata=bounds(min=-1e9, max=1e9))
    """Lowest atom."""
    vmax: float = field(default=100.0, metadata=bounds(min=-1e9, max=1e9))
    """Highest atom."""
    gamma: float = field(default=0.99, metadata=FRACTION)
    """Discount (of the n-step reward too)."""
    n_step: int = field(default=1, metadata=bounds(min=1, max=1000))
    """Steps of the return the data layer sums (transition batches only)."""
    target_update_period: int = field(default=100, metadata=STEPS)
    """Learner steps between hard copies into the target policy and critic."""
    prior_lr: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the ABM prior."""
    policy_lr: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the policy."""
    critic_lr: float = field(default=1e-4, metadata=LEARNING_RATE)
    """Adam learning rate of the critic."""
    dual_lr: float = field(default=1e-2, metadata=LEARNING_RATE)
    """Adam learning rate of MPO's temperature and KL multipliers (Acme's MPO: 1e-2)."""
    num_samples: int = field(default=20, metadata=bounds(min=1, max=10_000))
    """Actions sampled per state for the E-step, the advantage baseline and the critic target."""
    epsilon: float = field(default=0.1, metadata=bounds(gt=0.0, max=1e3))
    """KL bound of the E-step (temperature dual)."""
    epsilon_mean: float = field(default=2.5e-3, metadata=bounds(gt=0.0, max=1e3))
    """KL bound on the policy mean's move per update."""
    epsilon_std: float = field(default=1e-6, metadata=bounds(gt=0.0, max=1e3))
    """KL bound on the policy standard deviation's move per update."""
    advantage_weights: str = "binary"
    """ABM prior weights: 'binary' (1[A >= 0], ABM+) or 'exp' (exp(A / advantage_temperature))."""
    advantage_temperature: float = field(default=1.0, metadata=bounds(gt=0.0, max=1e6))
    """Temperature of the 'exp' advantage weights."""
    eval_variance: float = field(default=1e-4, metadata=bounds(min=1e-12, max=1e6))
    """Variance of the policy when acting greedily (the paper's evaluation, as BC's)."""
    batch_size: int = field(default=1024, metadata=BATCH)
    """Transitions per update; windows per update when recurrent (as BC: 1024 and 128)."""
    num_steps: int = field(default=1_000_000, metadata=STEPS)
    """Learner steps of a full run: what ``rlu train`` runs when no --steps is given. The paper
    states no budget for the continuous baselines; 1M is rlu's choice."""


Config = RABMConfig
PRESETS = {
    "paper": RABMConfig(),
    "paper_recurrent": RABMConfig(recurrent=True, batch_size=128),  # the sequence tasks
    # Minutes on a CPU: the trust region may move further, and its anchor sooner, than at
    # paper scale (where 100-step targets and eps_mean 2.5e-3 act over a million updates).
    "small": RABMConfig(hidden_size=256, num_layers=2, lstm_hidden=64, sequence_length=10,
                        prior_lr=1e-3, policy_lr=1e-3, critic_lr=1e-3, batch_size=256,
                        target_update_period=10, epsilon_mean=0.05, epsilon_std=1e-3,
                        num_samples=10, num_steps=20_000),
}  # fmt: skip
GRID: dict[str, list] = {}  # the paper reports no sweep for RABM


class GaussianPolicy(nn.Module):
    def __init__(self, observation_spec: ObservationSpec, action_dim: int, c: RABMConfig) -> None:
        super().__init__()
        lstm = c.lstm_hidden if c.recurrent else 0
        self.torso = nets.Torso(
            observation_spec, c.hidden_size, c.num_layers, lstm, torso_hidden=c.torso_hidden
        )
        self.head = nets.GaussianHead(self.torso.output_dim, action_dim)


class Critic(nn.Module):
    def __init__(self, observation_spec: ObservationSpec, action_dim: int, c: RABMConfig) -> None:
        super().__init__()
        lstm = c.lstm_hidden if c.recurrent else 0
        self.torso = nets.Torso(
            observation_spec, c.hidden_size, c.num_layers, lstm, torso_hidden=c.torso_hidden
        )
        h = self.torso.output_dim
        self.joint = nn.Linear(h + action_dim, h)
        self.head = nets.CategoricalHead(h, c.num_atoms, c.vmin, c.vmax)

    def logits(self, features: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """(M, H) features with (M, A) or (N, M, A) actions -> logits (..., atoms)."""
        f = features.expand(*action.shape[:-1], features.shape[-1])
        return self.head(F.elu(self.joint(torch.cat([f, action], -1))))


def prior_loss(
    log_prob: torch.Tensor, advantage: torch.Tensor, kind: str, temperature: float
) -> tuple[torch.Tensor, common.Metrics]:
    """ABM: advantage-weighted log-likelihood of the data's actions under the prior."""
    w = losses.abm_weights(advantage.detach(), kind, temperature)
    loss = -(w * log_prob).mean()
    return loss, {"prior/loss": loss, "prior/weight_mean": w.mean()}


def mpo_m_step(
    weights: torch.Tensor,
    samples: torch.Tensor,
    mean: torch.Tensor,
    std: torch.Tensor,
    target_mean: torch.Tensor,
    target_std: torch.Tensor,
    duals: nn.ParameterDict,
    c: RABMConfig,
) -> tuple[torch.Tensor, common.Metrics]:
    """Decoupled MPO M-step: weighted ML of the prior's samples plus KL trust regions."""
    logp_mean = losses.gaussian_log_prob(mean, target_std, samples)  # (N, M): mean moves, std fixed
    logp_std = losses.gaussian_log_prob(target_mean, std, samples)
    loss_fit = -(weights * (logp_mean + logp_std)).sum(0).mean()
    kl_mean = losses.gaussian_kl(target_mean, target_std, mean, target_std).mean()
    kl_std = losses.gaussian_kl(target_mean, target_std, target_mean, std).mean()
    alpha_mean = F.softplus(duals["log_alpha_mean"]) + 1e-8
    alpha_std = F.softplus(duals["log_alpha_std"]) + 1e-8
    loss_kl = alpha_mean.detach() * kl_mean + alpha_std.detach() * kl_std
    loss_alpha = alpha_mean * (c.epsilon_mean - kl_mean.detach()) + alpha_std * (
        c.epsilon_std - kl_std.detach()
    )
    metrics = {"actor/loss": loss_fit, "actor/kl_mean": kl_mean, "actor/kl_std": kl_std,
               "dual/alpha_mean": alpha_mean, "dual/alpha_std": alpha_std}  # fmt: skip
    return loss_fit + loss_kl + loss_alpha, metrics


class RABMAgent:
    def __init__(
        self,
        observation_spec: ObservationSpec,
        action_spec: ActionSpec,
        config: RABMConfig,
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        self.config, self.device, self.step = config, common.device(device), 0
        self.scaler = nets.ActionScaler(action_spec)
        self.num_steps, self.pretrain_steps = config.num_steps, 0
        if config.recurrent:  # windows train on 1-step targets inside them
            self.batch_spec = BatchSpec(
                config.batch_size, "sequence", sequence_length=config.sequence_length,
                gamma=config.gamma,
            )  # fmt: skip
        else:
            self.batch_spec = BatchSpec(config.batch_size, n_step=config.n_step, gamma=config.gamma)
        self.generator = common.generator(stream_seed(seed, "learner"), self.device)
        a, d = self.scaler.dim, self.device
        with common.seeded(seed):
            self.prior = GaussianPolicy(observation_spec, a, config).to(d)
            self.policy = GaussianPolicy(observation_spec, a, config).to(d)
            self.critic = Critic(observation_spec, a, config).to(d)
        self.target_policy = common.frozen_copy(self.policy)
        self.target_critic = common.frozen_copy(self.critic)
        self.duals = nn.ParameterDict({
            "log_temperature": nn.Parameter(torch.tensor(1.0)),
            "log_alpha_mean": nn.Parameter(torch.tensor(1.0)),
            "log_alpha_std": nn.Parameter(torch.tensor(10.0)),
        }).to(d)  # fmt: skip
        self.optimizers = {
            "prior": common.adam(self.prior.parameters(), config.prior_lr),
            "policy": common.adam(self.policy.parameters(), config.policy_lr),
            "critic": common.adam(self.critic.parameters(), config.critic_lr),
            "dual": common.adam(self.duals.parameters(), config.dual_lr),
        }
        act_seed = stream_seed(seed, "act")
        self.generators = {"sample": self.generator, "act": common.generator(act_seed, d)}
        self.modules = {
            "prior": self.prior, "policy": self.policy, "critic": self.critic, "duals": self.duals,
            "target_policy": self.target_policy, "target_critic": self.target_critic,
        }  # fmt: skip
        # copied into their targets every target_update_period updates
        self.targets = {self.target_policy: self.policy, self.target_critic: self.critic}
        self._rollout_state: common.LSTMState | None = None

    def _features(
        self,
        torso: nets.Torso,
        batch: _Prepared,
        seq: bool,
        valid: torch.Tensor | None,
        which: str,
    ) -> torch.Tensor:
        """Torso output at s ('cur') or s' ('next') of every valid transition: (M, H)."""
        if seq:
            h, _ = torso(batch.obs, sequence=True)
            h = h[:, :-1] if which == "cur" else h[:, 1:]
            return h.reshape(-1, h.shape[-1])[valid]
        return torso(batch.obs if which == "cur" else batch.next_obs)[0]

    def update(self, batch: Transition | Sequence) -> dict[str, float]:
        c, g = self.config, self.generator
        seq = isinstance(batch, Sequence)
        b = _Prepared(batch, self.scaler, self.device)
        valid = b.valid
        atoms = self.critic.head.atoms
        n = c.num_samples

        def feats(module: GaussianPolicy | Critic, which: str) -> torch.Tensor:
            return self._features(module.torso, b, seq, valid, which)

        pol_h, prior_h = feats(self.policy, "cur"), feats(self.prior, "cur")
        crit_h = feats(self.critic, "cur")
        with torch.no_grad():
            # Critic target: the target policy's actions at s', distributions averaged over them.
            t_mean, t_std = self.target_policy.head(feats(self.target_policy, "next"))
            noise = torch.randn((n, *t_mean.shape), generator=g, device=t_mean.device)
            next_a = (t_mean + t_std * noise).clamp(-1, 1)
            t_logits = self.target_critic.logits(feats(self.target_critic, "next"), next_a)
            t_probs = torch.softmax(t_logits, -1).mean(0)
            values = losses.bootstrap_values(b.reward, b.discount, self.batch_spec.bootstrap_gamma,
                                      atoms.expand(b.reward.shape[0], -1))  # fmt: skip
            target = losses.categorical_projection(values, t_probs, atoms)
        loss_critic = losses.categorical_cross_entropy(
            self.critic.logits(crit_h, b.action), target
        ).mean()
        metrics = {"critic/loss": loss_critic}

        mean, std = self.policy.head(pol_h)
        prior_mean, prior_std = self.prior.head(prior_h)
        with torch.no_grad():
            crit_d = crit_h.detach()
            q_data = self.critic.head.mean(self.critic.logits(crit_d, b.action))
            noise = torch.randn((n, *mean.shape), generator=g, device=mean.device)
            pi_a = (mean + std * noise).clamp(-1, 1)
            advantage = q_data - self.critic.head.mean(self.critic.logits(crit_d, pi_a)).mean(0)
            noise = torch.randn((n, *mean.shape), generator=g, device=mean.device)
            prior_a = prior_mean + prior_std * noise
            prior_a = prior_a.clamp(-1, 1)
            q_prior = self.critic.head.mean(self.critic.logits(crit_d, prior_a))
            tp_mean, tp_std = self.target_policy.head(feats(self.target_policy, "cur"))
        metrics["critic/q_mean"] = q_data.mean()
        loss_prior, m = prior_loss(
            losses.gaussian_log_prob(prior_mean, prior_std, b.action), advantage,
            c.advantage_weights, c.advantage_temperature,
        )  # fmt: skip
        metrics.update(m)
        temperature = F.softplus(self.duals["log_temperature"]) + 1e-8
        weights, loss_temperature = losses.mpo_e_step(q_prior, temperature, c.epsilon)
        loss_policy, m = mpo_m_step(weights, prior_a, mean, std, tp_mean, tp_std, self.duals, c)
        metrics.update(m)
        metrics["dual/temperature"] = temperature

        # Each loss reaches only its own network's parameters, so one backward serves all four.
        loss = loss_critic + loss_prior + loss_policy + loss_temperature
        common.joint_step(self.optimizers.values(), loss)
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
        """The Gaussian's mean plus noise of variance ``eval_variance`` (the paper's evaluation)
        with ``greedy=True``; with ``greedy=False`` a sample of the learnt Gaussian."""
        obs = common.to_torch(observation, self.device)
        state = nets.carried_state(self._rollout_state, is_first, obs)
        h, self._rollout_state = self.policy.torso(obs, state=state)
        mean, std = self.policy.head(h)
        if greedy:
            std = torch.full_like(std, self.config.eval_variance**0.5)
        noise = torch.randn(mean.shape, generator=self.generators["act"], device=mean.device)
        return self.scaler.from_unit(mean + std * noise)

    def state_dict(self) -> dict:
        return common.agent_state(self.modules, self.optimizers, self.generators, self.step)

    def load_state_dict(self, state: dict) -> None:
        self.step = common.load_agent_state(state, self.modules, self.optimizers, self.generators)
        self._rollout_state = None  # acting restarts after a restore


class _Prepared:
    """A batch as tensors, flattened to its valid transitions (all of them for Transitions)."""

    def __init__(
        self, batch: Transition | Sequence, scaler: nets.ActionScaler, device: torch.device
    ) -> None:
        self.obs = common.to_torch(batch.observation, device)
        action = scaler.to_unit(common.to_torch(batch.action, device))
        reward = common.to_torch(batch.reward, device)
        discount = common.to_torch(batch.discount, device)
        self.valid: torch.Tensor | None
        if isinstance(batch, Sequence):
            m = common.to_torch(batch.mask, device)
            last = common.to_torch(batch.is_last, device)
            self.valid = (m[:, :-1] & m[:, 1:] & ~last[:, :-1]).reshape(-1)
            action = action[:, :-1].reshape(-1, action.shape[-1])[self.valid]
            reward = reward[:, :-1].reshape(-1)[self.valid]
            discount = discount[:, :-1].reshape(-1)[self.valid]
        else:
            self.valid = None
            self.next_obs = common.to_torch(batch.next_observation, device)
        self.action, self.reward, self.discount = action, reward.float(), discount.float()


Agent = RABMAgent
