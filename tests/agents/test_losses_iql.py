"""IQL's expectile, critic and AWR losses and its policy schedule, on hand-computed inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import iql, make_agent  # noqa: E402
from tests.fakes import CONT_ACTION, LOWDIM_OBS, fake_transition  # noqa: E402


def t(x):
    return torch.tensor(x, dtype=torch.float32)


def close(a, b, tol=1e-6):
    a, b = (x.detach() if isinstance(x, torch.Tensor) else x for x in (a, b))
    np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), atol=tol)


def test_expectile_loss_weights_positive_errors_by_tau():
    close(iql.expectile_loss(t([2.0, -1.0]), 0.7), (0.7 * 4.0 + 0.3 * 1.0) / 2)  # 1.55
    close(iql.expectile_loss(t([2.0, -1.0]), 0.5), 0.5 * (4.0 + 1.0) / 2)  # plain MSE / 2


def test_value_loss_is_minimised_at_the_expectile():
    # Two equally likely returns 0 and 1: the 0.9-expectile v solves 0.9 (1 - v) = 0.1 v -> 0.9.
    q = t([0.0, 1.0])
    for v0, zero in ((0.9, True), (0.5, False)):
        v = torch.full((2,), v0, requires_grad=True)
        loss, metrics = iql.value_loss(q, v, 0.9)
        loss.backward()
        assert (abs(float(v.grad.sum())) < 1e-6) is zero
        close(metrics["value/v_mean"], v0)
    q = t([0.0, 1.0]).requires_grad_()
    iql.value_loss(q, torch.zeros(2, requires_grad=True), 0.9)[0].backward()
    assert q.grad is None  # the target critics' Q is held fixed


def test_critic_loss_sums_the_twin_mean_squared_errors():
    loss, metrics = iql.critic_loss(t([[1.0, 2.0], [3.0, 4.0]]), t([1.0, 1.0]))
    close(loss, (0.0 + 1.0) / 2 + (4.0 + 9.0) / 2)  # 7
    close(metrics["critic/q_mean"], 2.5)


def test_awr_weights_and_actor_loss():
    close(iql.awr_weights(t([0.0, 1.0, 2.0]), 3.0, 100.0), [1.0, math.exp(3.0), 100.0])
    adv = t([0.0, math.log(2.0) / 3.0]).requires_grad_()  # weights 1 and 2 at beta = 3
    loss, metrics = iql.actor_loss(t([-1.0, -2.0]), adv, 3.0, 100.0)
    close(loss, -(1.0 * -1.0 + 2.0 * -2.0) / 2, 1e-6)  # 2.5
    close(metrics["actor/weight_mean"], 1.5, 1e-6)
    assert not loss.requires_grad  # no gradient reaches the advantage


def test_cosine_schedule_matches_optax():
    # optax.cosine_decay_schedule(1e-3, 100): 1e-3 at 0, half at 50, 0 from 100 on.
    close(iql.cosine_lr(1e-3, 0, 100), 1e-3)
    close(iql.cosine_lr(1e-3, 50, 100), 5e-4)
    close(iql.cosine_lr(1e-3, 25, 100), 1e-3 * 0.5 * (1 + math.cos(math.pi / 4)))
    close(iql.cosine_lr(1e-3, 100, 100), 0.0)
    close(iql.cosine_lr(1e-3, 150, 100), 0.0)


def test_the_policy_steps_with_the_scheduled_rate_and_the_critics_with_a_fixed_one():
    agent = make_agent("iql", LOWDIM_OBS, CONT_ACTION, hidden_layers=(16,), num_steps=4)
    batch = fake_transition(LOWDIM_OBS, CONT_ACTION, 8)
    for k in range(3):
        agent.update(batch)
        close(agent.optimizers["policy"].param_groups[0]["lr"], iql.cosine_lr(3e-4, k, 4))
        close(agent.optimizers["critic"].param_groups[0]["lr"], 3e-4)
    constant = make_agent("iql", LOWDIM_OBS, CONT_ACTION, hidden_layers=(16,), num_steps=4,
                          cosine_decay=False)  # fmt: skip
    for _ in range(3):
        constant.update(batch)
    close(constant.optimizers["policy"].param_groups[0]["lr"], 3e-4)


def test_reward_scale_multiplies_the_rewards_in_the_critic_target():
    batch = fake_transition(LOWDIM_OBS, CONT_ACTION, 8)
    scaled = batch._replace(reward=batch.reward * 10.0)
    a = make_agent("iql", LOWDIM_OBS, CONT_ACTION, hidden_layers=(16,), reward_scale=10.0)
    b = make_agent("iql", LOWDIM_OBS, CONT_ACTION, hidden_layers=(16,))
    assert a.update(batch) == b.update(scaled)
