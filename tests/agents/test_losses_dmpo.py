"""DMPO's losses against Acme's formulas written out in numpy; its duals, critic target, acting."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import dmpo, make_agent, make_config  # noqa: E402
from rlu.agents.losses import categorical_projection  # noqa: E402
from tests.fakes import CONT_ACTION, LOWDIM_OBS, fake_transition  # noqa: E402


def softplus(x):
    return np.log1p(np.exp(x))


def normal_log_prob(mean, std, x):
    return (-0.5 * ((x - mean) / std) ** 2 - np.log(std) - 0.5 * math.log(2 * math.pi)).sum(-1)


def kl_per_dim(mp, sp, mq, sq):
    return np.log(sq / sp) + (sp**2 + (mp - mq) ** 2) / (2 * sq**2) - 0.5


def acme_mpo_loss(mean, std, t_mean, t_std, actions, q, logs, c):
    """acme/tf/losses/mpo.py (per-dimension constraints, action penalization), in numpy."""
    temp, pen_temp, a_mean, a_std = (softplus(np.asarray(v, np.float64)) + 1e-8 for v in logs)

    def weights_and_dual(values, eps, eta):
        z = values / eta
        w = np.exp(z - z.max(0)) / np.exp(z - z.max(0)).sum(0)
        lse = np.log(np.exp(z).sum(0))
        return w, eta * (eps + lse.mean() - math.log(values.shape[0]))

    w, loss_t = weights_and_dual(q, c.epsilon, temp)
    cost = -np.linalg.norm(actions - np.clip(actions, -1, 1), axis=-1)
    wp, loss_tp = weights_and_dual(cost, c.epsilon_penalty, pen_temp)
    w = w + wp
    ce_mean = -(normal_log_prob(mean, t_std, actions) * w).sum(0).mean()
    ce_std = -(normal_log_prob(t_mean, std, actions) * w).sum(0).mean()
    kl_m = kl_per_dim(t_mean, t_std, mean, t_std).mean(0)
    kl_s = kl_per_dim(t_mean, t_std, t_mean, std).mean(0)
    loss_kl = (a_mean * kl_m).sum() + (a_std * kl_s).sum()
    loss_alpha = (a_mean * (c.epsilon_mean - kl_m)).sum()
    loss_alpha += (a_std * (c.epsilon_stddev - kl_s)).sum()
    return ce_mean + ce_std + loss_kl + loss_alpha + loss_t + loss_tp


def test_mpo_loss_is_acmes():
    rng = np.random.default_rng(0)
    n, b, a = 5, 4, 3
    mean, t_mean = rng.normal(size=(b, a)), rng.normal(size=(b, a))
    std, t_std = rng.uniform(0.2, 1.0, (b, a)), rng.uniform(0.2, 1.0, (b, a))
    actions = rng.normal(0, 1.2, (n, b, a))  # some beyond [-1, 1]: the penalty acts
    q = rng.normal(0, 5, (n, b))
    logs = (0.5, -1.0, rng.normal(size=a), rng.normal(size=a))
    c = dmpo.DMPOConfig(epsilon_mean=0.01, epsilon_stddev=1e-4)
    duals = {k: torch.tensor(v, dtype=torch.float64) for k, v in zip(
        ("log_temperature", "log_penalty_temperature", "log_alpha_mean", "log_alpha_stddev"), logs,
        strict=True)}  # fmt: skip
    T = lambda x: torch.tensor(x, dtype=torch.float64)  # noqa: E731
    loss, metrics = dmpo.mpo_loss(T(mean), T(std), T(t_mean), T(t_std), T(actions), T(q), duals, c)
    want = acme_mpo_loss(mean, std, t_mean, t_std, actions, q, logs, c)
    np.testing.assert_allclose(float(loss), want, rtol=1e-10)
    np.testing.assert_allclose(float(metrics["dual/temperature"]), softplus(0.5) + 1e-8)


def test_duals_move_towards_their_bounds():
    """A KL above its bound raises its multiplier; the temperature's dual gradient is Acme's."""
    b, a, n = 8, 2, 6
    t_mean, t_std = torch.zeros(b, a), torch.ones(b, a)
    mean = torch.full((b, a), 0.5)  # KL of the mean: 0.125 per dimension, far above 0.01
    std = torch.ones(b, a)  # the std has not moved: KL 0, below its bound
    duals = {"log_temperature": torch.tensor(0.0, requires_grad=True),
             "log_penalty_temperature": torch.tensor(0.0, requires_grad=True),
             "log_alpha_mean": torch.zeros(a, requires_grad=True),
             "log_alpha_stddev": torch.zeros(a, requires_grad=True)}  # fmt: skip
    actions = torch.zeros(n, b, a)
    q = torch.zeros(n, b)
    c = dmpo.DMPOConfig(epsilon_mean=0.01, epsilon_stddev=1e-3)
    loss, _ = dmpo.mpo_loss(mean, std, t_mean, t_std, actions, q, duals, c)
    loss.backward()
    assert (duals["log_alpha_mean"].grad < 0).all()  # descent raises alpha_mean
    assert (duals["log_alpha_stddev"].grad > 0).all()  # descent lowers alpha_stddev
    # equal Q everywhere: weights uniform, the temperature's loss is eta * epsilon, its
    # gradient epsilon * sigmoid(log eta) (softplus' derivative)
    np.testing.assert_allclose(float(duals["log_temperature"].grad), c.epsilon * 0.5, rtol=1e-6)


def test_critic_target_averages_the_sampled_actions_distributions():
    atoms = torch.linspace(-2.0, 2.0, 5)
    sampled = torch.randn(4, 3, 5, generator=torch.Generator().manual_seed(0))  # (N, B, K)
    reward, discount = torch.tensor([0.5, -1.0, 0.0]), torch.tensor([1.0, 1.0, 0.0])
    logits = torch.randn(3, 5, generator=torch.Generator().manual_seed(1)).requires_grad_()
    loss, _ = dmpo.critic_loss(logits, sampled, reward, discount, atoms, 0.9)
    probs = torch.softmax(sampled, -1).mean(0)
    target = categorical_projection(reward[:, None] + 0.9 * discount[:, None] * atoms, probs, atoms)
    want = -(target * torch.log_softmax(logits.detach(), -1)).sum(-1).mean()
    np.testing.assert_allclose(float(loss.detach()), float(want), rtol=1e-6)
    loss.backward()
    assert sampled.grad is None  # the target side takes no gradient


def test_policy_head_starts_at_init_scale_and_acting_clips():
    agent = make_agent("dmpo", LOWDIM_OBS, CONT_ACTION, preset="small", seed=0)
    batch = fake_transition(LOWDIM_OBS, CONT_ACTION, batch=16)
    mean, std = agent.policy(agent.policy.encoder.flatten(
        {k: torch.as_tensor(v) for k, v in batch.observation.items()}))  # fmt: skip
    np.testing.assert_allclose(std.detach().numpy(), 0.7, atol=1e-3)  # Acme's init_scale
    assert float(mean.detach().abs().max()) < 0.05  # a near-zero mean layer
    greedy = agent.act(batch.observation, greedy=True)
    np.testing.assert_allclose(greedy, np.clip(mean.detach().numpy(), -1, 1), atol=1e-6)
    sampled = np.stack([agent.act(batch.observation, greedy=False) for _ in range(50)])
    assert sampled.min() >= -1.0 and sampled.max() <= 1.0
    assert 0.4 < sampled.std(0).mean() < 0.8  # a 0.7 Gaussian, clipped to the bounds


def test_updates_respect_the_duals_floor_and_the_paper_preset_is_acmes():
    agent = make_agent("dmpo", LOWDIM_OBS, CONT_ACTION, preset="small", seed=0)
    with torch.no_grad():
        agent.duals["log_temperature"].fill_(-50.0)
    metrics = agent.update(fake_transition(LOWDIM_OBS, CONT_ACTION, batch=128))
    assert float(agent.duals["log_temperature"]) >= dmpo.MIN_LOG_DUAL - 1.0  # projected first
    assert all(np.isfinite(v) for v in metrics.values())
    c = make_config("dmpo", False, "paper")
    assert (c.num_samples, c.n_step, c.epsilon, c.epsilon_mean, c.epsilon_stddev) == (
        20, 5, 0.1, 2.5e-3, 1e-6)  # fmt: skip
    assert (c.init_log_temperature, c.init_log_alpha_mean, c.init_log_alpha_stddev) == (
        10.0, 10.0, 1000.0)  # fmt: skip
    assert (c.vmin, c.vmax, c.num_atoms, c.max_grad_norm) == (-150.0, 150.0, 51, 40.0)
