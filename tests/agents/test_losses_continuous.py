"""Exact numbers for every loss and target of the continuous agents, on tiny hand-made inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import bcq, brac, d4pg, make_agent  # noqa: E402
from rlu.agents import losses as L  # noqa: E402
from rlu.agents import networks as nets  # noqa: E402
from tests.fakes import CONT_ACTION, LOWDIM_OBS, fake_transition  # noqa: E402

LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


def t(x):
    return torch.tensor(x, dtype=torch.float32)


def close(a, b, tol=1e-6):
    np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), atol=tol)


def test_categorical_projection_splits_mass_between_neighbours_and_clips_the_ends():
    atoms = t([0.0, 1.0, 2.0])
    # 0.5 lies halfway between atoms 0 and 1; 1.0 sits on atom 1; 5.0 and -3.0 are clipped.
    values = t([[0.5, 1.0, 5.0], [-3.0, 1.75, 2.0]])
    probs = t([[0.2, 0.3, 0.5], [0.4, 0.4, 0.2]])
    out = L.categorical_projection(values, probs, atoms)
    close(out, [[0.1, 0.4, 0.5], [0.4, 0.1, 0.5]])
    close(out.sum(-1), [1.0, 1.0])


def test_categorical_projection_of_a_shifted_support_on_atoms_of_width_two():
    atoms = t([-2.0, 0.0, 2.0])
    values = atoms * 0.5 + 1.0  # r = 1, gamma d = 0.5 -> [0, 1, 2]
    out = L.categorical_projection(values[None], t([[0.5, 0.25, 0.25]]), atoms)
    close(out, [[0.0, 0.5 + 0.125, 0.125 + 0.25]])


def test_n_step_target_bootstraps_with_gamma_to_the_n():
    values = L.bootstrap_values(t([2.75, 1.0]), t([1.0, 0.0]), 0.5**3, t([[4.0, 8.0], [4.0, 8.0]]))
    close(values, [[2.75 + 0.125 * 4, 2.75 + 0.125 * 8], [1.0, 1.0]])


def test_d4pg_critic_loss_is_cross_entropy_to_the_projected_target():
    atoms = t([0.0, 1.0, 2.0])
    target_logits = torch.log(t([[0.0 + 1e-30, 1.0, 0.0 + 1e-30]]))  # next state: all mass at 1
    logits = torch.log(t([[0.25, 0.5, 0.25]]))
    # r = 0.5, gamma^n d = 0.5: 1 -> 1.0 exactly, so the target is [0, 1, 0].
    loss, metrics = d4pg.critic_loss(logits, target_logits, t([0.5]), t([1.0]), atoms, 0.5)
    close(loss, -math.log(0.5))
    close(metrics["critic/q_mean"], 1.0)


def test_d4pg_policy_gradient_clips_dq_da_per_example_as_acmes_dpg_loss():
    # Q(a) = sigmoid(k . a) over atoms {0, 1}; at a = 0, dQ/da = k / 4 = [1, 0.75] (norm 1.25).
    k, atoms = t([4.0, 3.0]), t([0.0, 1.0])

    def logits(a):
        z = (a * k).sum(-1)
        return torch.stack([torch.zeros_like(z), z], -1)

    a = torch.zeros(2, 2, requires_grad=True)
    loss, metrics = d4pg.policy_loss(logits(a), atoms, a, dqda_clip_norm=1.0)
    close(loss.detach(), 0.5 * (0.8**2 + 0.6**2))  # Acme's 0.5 ||clip(dQ/da)||^2, batch mean
    close(metrics["actor/loss"], -0.5)
    close(metrics["actor/dqda_norm"], 1.25)
    close(torch.autograd.grad(loss, a)[0], [[-0.4, -0.3], [-0.4, -0.3]])  # -[0.8, 0.6] / B
    # a norm under the clip leaves dQ/da alone: the gradient of -E[Q], the unclipped loss's
    loss, _ = d4pg.policy_loss(logits(a), atoms, a, dqda_clip_norm=10.0)
    unclipped, _ = d4pg.policy_loss(logits(a), atoms)
    close(torch.autograd.grad(loss, a)[0], [[-0.5, -0.375], [-0.5, -0.375]])
    close(torch.autograd.grad(unclipped, a)[0], [[-0.5, -0.375], [-0.5, -0.375]])
    close(unclipped.detach(), -0.5)


def test_d4pg_paper_preset_is_the_notebooks_offline_learner():
    c = d4pg.PRESETS["paper"]
    assert (c.n_step, c.gamma, c.target_update_period, c.batch_size) == (1, 0.99, 100, 256)
    assert (c.max_grad_norm, c.dqda_clip_norm) == (40.0, 1.0)  # Acme's clipping=True
    assert (c.policy_lr, c.critic_lr) == (1e-4, 1e-4)


def test_mixture_log_likelihood():
    # Equal weights, unit components at 0 and 2, action 1: both densities equal N(1; 0, 1).
    lp = L.mixture_log_prob(t([[0.0, 0.0]]), t([[[0.0], [2.0]]]), t([[[1.0], [1.0]]]), t([[1.0]]))
    close(lp, [-0.5 - LOG_SQRT_2PI])
    # Weights 3:1, std 1 and 2, action 0: (0.75 + 0.25 / 2) / sqrt(2 pi).
    lp = L.mixture_log_prob(
        t([[math.log(3.0), 0.0]]), t([[[0.0], [0.0]]]), t([[[1.0], [2.0]]]), t([[0.0]])
    )
    close(lp, [math.log(0.875) - LOG_SQRT_2PI])
    # Two action dimensions multiply: N(0;0,1) N(1;0,1).
    lp = L.mixture_log_prob(t([[0.0]]), t([[[0.0, 0.0]]]), t([[[1.0, 1.0]]]), t([[0.0, 1.0]]))
    close(lp, [-0.5 - 2 * LOG_SQRT_2PI])


def test_vae_loss():
    loss, metrics = L.vae_loss(t([[0.5]]), t([[1.0]]), t([[0.0, 1.0]]), t([[1.0, 0.5]]))
    kl = (0.0 + -0.5 * (1 + math.log(0.25) - 1.0 - 0.25)) / 2
    close(metrics["vae/recon_loss"], 0.25)
    close(metrics["vae/kl"], kl)
    close(loss, 0.25 + 0.5 * kl)


def test_bcq_soft_clipped_double_q():
    close(bcq.clipped_double_q(t([1.0, 4.0]), t([3.0, 2.0]), 0.75), [1.5, 2.5])


def test_brac_kl_estimate_is_the_mean_log_ratio_over_samples():
    log_pi = t([[-1.0, -2.0], [-3.0, -4.0]])  # (S=2, B=2)
    log_b = t([[-2.0, -2.0], [-2.0, -6.0]])
    close(L.sample_kl(log_pi, log_b), [0.0, 1.0])


def test_brac_kl_estimate_converges_to_the_closed_form_for_gaussians():
    g = torch.Generator().manual_seed(0)
    mean_p, std_p, mean_b, std_b = t([0.3]), t([0.5]), t([0.0]), t([1.0])
    a = mean_p + std_p * torch.randn((200_000, 1, 1), generator=g)
    est = L.sample_kl(L.gaussian_log_prob(mean_p, std_p, a), L.gaussian_log_prob(mean_b, std_b, a))
    close(est, L.gaussian_kl(mean_p, std_p, mean_b, std_b)[None], 5e-3)


def test_tanh_gaussian_log_prob_change_of_variables():
    close(L.tanh_gaussian_log_prob(t([0.0]), t([1.0]), t([0.0])), -LOG_SQRT_2PI)
    expected = -0.5 - LOG_SQRT_2PI - math.log(1 - math.tanh(1.0) ** 2)
    close(L.tanh_gaussian_log_prob(t([0.0]), t([1.0]), t([1.0])), expected, 1e-5)


def test_brac_actor_loss_is_the_value_penalty():
    loss, _ = brac.actor_loss(t([1.0, 3.0]), t([0.5, 1.5]), alpha=0.3)
    close(loss, ((0.3 * 0.5 - 1.0) + (0.3 * 1.5 - 3.0)) / 2)


def test_abm_advantage_weights():
    adv = t([-1.0, 0.0, 2.0])
    close(L.abm_weights(adv, "binary"), [0.0, 1.0, 1.0])
    e = np.exp([-1.0, 0.0, 2.0])
    close(L.abm_weights(adv, "exp", 1.0), 3 * e / e.sum())
    with pytest.raises(ValueError, match="binary"):
        L.abm_weights(adv, "linear")


def test_mpo_e_step_weights_and_temperature_dual():
    q = t([[0.0, 1.0], [math.log(3.0), 1.0]])  # (N=2 samples, B=2 states)
    weights, dual = L.mpo_e_step(q, t(1.0), epsilon=0.1)
    close(weights, [[0.25, 0.5], [0.75, 0.5]])
    # eta eps + eta mean_b (logsumexp_n(Q/eta) - log N): state 0 -> log 2, state 1 -> 1.
    close(dual, 0.1 + (math.log(2.0) + 1.0) / 2)
    weights, _ = L.mpo_e_step(q, t(0.5), epsilon=0.1)  # colder: q^2 normalised
    close(weights[:, 0], [0.1, 0.9])


def test_gaussian_kl_closed_form():
    close(L.gaussian_kl(t([0.0]), t([1.0]), t([1.0]), t([2.0])), math.log(2) + 2 / 8 - 0.5)


def test_brac_warm_start_trains_the_policy_on_the_kl_alone_then_adds_q():
    kw = dict(policy_layers=(16,), critic_layers=(16,), behaviour_layers=(16,), alpha=0.3,
              behaviour_steps=1, warm_start_steps=2)  # fmt: skip
    agent = make_agent("brac", LOWDIM_OBS, CONT_ACTION, **kw)
    metrics = [agent.update(fake_transition(LOWDIM_OBS, CONT_ACTION, 8, i)) for i in range(4)]
    assert "actor/loss" not in metrics[0]  # the behaviour phase
    for m in metrics[1:3]:  # agent updates 0 and 1: alpha KL only
        close(m["actor/loss"], 0.3 * m["actor/kl"], 1e-6)
    assert abs(metrics[3]["actor/loss"] - 0.3 * metrics[3]["actor/kl"]) > 1e-3  # - Q joins


def test_brac_policy_log_std_is_squashed_into_the_originals_range():
    policy = nets.TanhGaussianPolicy(LOWDIM_OBS, 2, (8,), 16, (-5.0, 0.0), squash_log_std=True)
    with torch.no_grad():
        policy.net[-1].bias.copy_(t([0.0, 0.0, 50.0, -50.0]))  # raw log std +-50
        policy.net[-1].weight.zero_()
    obs = {
        k: torch.as_tensor(v)
        for k, v in fake_transition(LOWDIM_OBS, CONT_ACTION, 3).observation.items()
    }
    _, std = policy(obs)
    close(std.detach(), [[1.0, math.exp(-5.0)]] * 3)  # -5 + 2.5 (tanh(+-50) + 1) = 0, -5
    assert brac.LOG_STD_RANGE == (-5.0, 0.0)
