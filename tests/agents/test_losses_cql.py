"""CQL's regulariser, critic, entropy and policy losses on hand-computed inputs, its tanh-Gaussian
against torch.distributions, and the Lagrangian variant through the agent."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import cql, make_agent  # noqa: E402
from rlu.agents import networks as nets  # noqa: E402
from tests.fakes import CONT_ACTION, LOWDIM_OBS, fake_transition  # noqa: E402


def t(x):
    return torch.tensor(x, dtype=torch.float32)


def close(a, b, tol=1e-6):
    a, b = (x.detach() if isinstance(x, torch.Tensor) else x for x in (a, b))
    np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), atol=tol)


def test_regulariser_is_the_importance_sampled_log_sum_exp_minus_the_data_value():
    # One critic, one proposal of each kind, one state, A = 1 (uniform density 1/2):
    # terms 0 - log(1/2) = log 2, 2 - (2 - log 3) = log 3, 1 - (1 - log 5) = log 5.
    args = dict(q_rand=t([[[0.0]]]), q_curr=t([[[1.0]]]), q_next=t([[[2.0]]]),
                log_pi_curr=t([[1.0 - math.log(5.0)]]), log_pi_next=t([[2.0 - math.log(3.0)]]),
                q_data=t([[0.5]]), action_dim=1)  # fmt: skip
    close(cql.cql_regulariser(**args, temperature=1.0), [math.log(10.0) - 0.5], 1e-5)
    # Temperature T: T log sum exp(x / T).
    expected = 2.0 * math.log(math.sqrt(2.0) + math.sqrt(3.0) + math.sqrt(5.0)) - 0.5
    close(cql.cql_regulariser(**args, temperature=2.0), [expected], 1e-5)
    # A = 3: the uniform density is 1/8, its term 0 + 3 log 2.
    args["action_dim"] = 3
    close(cql.cql_regulariser(**args, temperature=1.0), [math.log(8.0 + 3.0 + 5.0) - 0.5], 1e-5)


def test_regulariser_averages_over_states_per_critic_and_pushes_data_values_up():
    q = torch.zeros((2, 1, 2))  # (C=2, N=1, B=2)
    q_data = t([[1.0, 3.0], [0.0, 0.0]]).requires_grad_()
    reg = cql.cql_regulariser(q, q, q, torch.zeros(1, 2), torch.zeros(1, 2), q_data, 1, 1.0)
    lse = math.log(2.0 + 1.0 + 1.0)  # log 2 + ... from the uniform term, exp(0) twice
    close(reg, [lse - 2.0, lse])
    reg.sum().backward()
    close(q_data.grad, [[-0.5, -0.5], [-0.5, -0.5]])  # minimising R raises Q on the data


def test_critic_loss_with_a_fixed_weight():
    loss, prime, metrics = cql.critic_loss(t([[1.0], [2.0]]), t([0.0]), t([0.5, 1.0]), 5.0)
    close(loss, (1.0 + 4.0) + 5.0 * (0.5 + 1.0))  # 12.5
    close(metrics["critic/td_loss"], 5.0)
    close(metrics["critic/regulariser"], 0.75)
    assert prime is None and "critic/alpha_prime" not in metrics


def test_critic_loss_with_the_lagrange_multiplier():
    alpha_prime = torch.tensor(2.0, requires_grad=True)
    reg = t([0.5, 1.0]).requires_grad_()
    loss, prime, metrics = cql.critic_loss(t([[1.0], [2.0]]), t([0.0]), reg, 5.0, alpha_prime, 3.0)
    # alpha' (w R - threshold) = 2 ([2.5, 5] - 3) = [-1, 4]
    close(loss, (1.0 + 4.0) + (-1.0 + 4.0))  # 8
    close(prime, -(2.0 * (2.5 - 3.0) + 2.0 * (5.0 - 3.0)) / 2)  # -1.5
    close(metrics["critic/alpha_prime"], 2.0)
    prime.backward()
    close(alpha_prime.grad, -((2.5 - 3.0) + (5.0 - 3.0)) / 2)  # over the threshold: alpha' grows
    assert reg.grad is None  # the multiplier's loss leaves the critics alone


def test_entropy_weight_loss_and_policy_losses():
    log_alpha = torch.tensor(0.5, requires_grad=True)
    loss, metrics = cql.alpha_loss(log_alpha, t([-1.0, -3.0]), target_entropy=-1.0)
    close(loss, -0.5 * ((-1.0 - 1.0) + (-3.0 - 1.0)) / 2)  # 1.5
    close(metrics["alpha/value"], math.exp(0.5))
    loss.backward()
    close(log_alpha.grad, 3.0)  # entropy 2 above the target -1: alpha shrinks
    loss, metrics = cql.policy_loss(t(0.5), t([-1.0, -2.0]), t([3.0, 1.0]))
    close(loss, ((0.5 * -1.0 - 3.0) + (0.5 * -2.0 - 1.0)) / 2)  # -2.75
    close(metrics["actor/entropy"], 1.5)
    loss, _ = cql.bc_policy_loss(t(0.5), t([-1.0]), t([-2.0]))
    close(loss, 0.5 * -1.0 + 2.0)


def test_tanh_gaussian_samples_and_densities_match_torch_distributions():
    from torch.distributions import Normal, TransformedDistribution
    from torch.distributions.transforms import TanhTransform

    g = torch.Generator().manual_seed(0)
    mean, std = t([[0.3, -1.0], [2.0, 0.0]]), t([[0.5, 1.0], [0.2, 2.0]])
    actions, log_prob = nets.sample_tanh_gaussian(mean, std, 7, g)
    assert actions.shape == (7, 2, 2) and log_prob.shape == (7, 2)
    assert torch.all(actions.abs() < 1.0)
    dist = TransformedDistribution(Normal(mean, std), [TanhTransform()])
    close(log_prob, dist.log_prob(actions.clamp(-0.999999, 0.999999)).sum(-1), 2e-3)


def test_lagrangian_variant_trains_its_multiplier_and_resumes_exactly():
    kw = dict(policy_layers=(16,), critic_layers=(16,), num_samples=2, bc_steps=1,
              lagrange_threshold=10.0)  # fmt: skip
    agent = make_agent("cql", LOWDIM_OBS, CONT_ACTION, **kw)
    assert set(agent.duals) == {"log_alpha", "log_alpha_prime"}
    batches = [fake_transition(LOWDIM_OBS, CONT_ACTION, 8, seed=i) for i in range(3)]
    metrics = agent.update(batches[0])
    assert metrics["critic/alpha_prime"] == 1.0  # exp(0) before its first step
    assert float(agent.duals["log_alpha_prime"].detach()) != 0.0
    buffer = io.BytesIO()
    torch.save(agent.state_dict(), buffer)
    buffer.seek(0)
    other = make_agent("cql", LOWDIM_OBS, CONT_ACTION, seed=5, **kw)
    other.load_state_dict(torch.load(buffer, weights_only=True))
    for batch in batches[1:]:
        assert agent.update(batch) == other.update(batch)
    fixed = make_agent("cql", LOWDIM_OBS, CONT_ACTION, policy_layers=(16,), critic_layers=(16,))
    assert set(fixed.duals) == {"log_alpha"} and "alpha_prime" not in fixed.optimizers


def test_target_entropy_defaults_to_minus_the_action_dimensions():
    agent = make_agent("cql", LOWDIM_OBS, CONT_ACTION, policy_layers=(16,), critic_layers=(16,))
    assert agent.target_entropy == -3.0
    agent = make_agent("cql", LOWDIM_OBS, CONT_ACTION, policy_layers=(16,), critic_layers=(16,),
                       target_entropy=-1.5)  # fmt: skip
    assert agent.target_entropy == -1.5
