"""ReBRAC's penalised target, critic and actor losses on hand-computed inputs; its networks
and initialisation; the original's order of the target updates; and its optional observation
normalisation through the dataset-statistics contract."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
from torch import nn  # noqa: E402

from rlu.agents import make_agent, rebrac  # noqa: E402
from rlu.types import DataStatistics, RluError  # noqa: E402
from tests.fakes import CONT_ACTION, LOWDIM_OBS, fake_transition  # noqa: E402

TINY = dict(actor_layers=(16, 16), critic_layers=(16, 16), torso_hidden=8)


def t(x):
    return torch.tensor(x, dtype=torch.float32)


def close(a, b, tol=1e-6):
    a, b = (x.detach() if isinstance(x, torch.Tensor) else x for x in (a, b))
    np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), atol=tol)


def test_critic_target_subtracts_the_penalty_on_the_next_action():
    target, metrics = rebrac.critic_target(
        t([1.0, 0.0]), t([1.0, 1.0]), 0.9, t([[2.0, 1.0], [3.0, 4.0]]),
        t([[0.5, 0.5], [0.0, 0.0]]), t([[0.0, 0.5], [1.0, -1.0]]), 0.1,
    )  # fmt: skip
    # min Q' = (2, 1); ||a' - a'_D||^2 summed over dimensions = (0.25, 2)
    close(target, [1.0 + 0.9 * (2.0 - 0.1 * 0.25), 0.0 + 0.9 * (1.0 - 0.1 * 2.0)])  # 2.7775, 0.72
    close(metrics["critic/bc_penalty"], 1.125)
    target, _ = rebrac.critic_target(
        t([1.0]), t([0.0]), 0.9, t([[2.0], [3.0]]), t([[1.0]]), t([[-1.0]]), 0.1
    )
    close(target, [1.0])  # after a terminal step neither Q' nor the penalty counts


def test_critic_loss_sums_the_twin_mean_squared_errors():
    target = t([1.0, 1.0]).requires_grad_()
    loss, metrics = rebrac.critic_loss(t([[1.0, 2.0], [3.0, 0.0]]), target)
    close(loss, (0.0 + 1.0) / 2 + (4.0 + 1.0) / 2)  # 3
    close(metrics["critic/q_min"], (1.0 + 0.0) / 2)
    assert not loss.requires_grad


def test_actor_loss_penalises_the_summed_squared_distance_and_normalises_q():
    q = t([2.0, -4.0]).requires_grad_()
    pi = t([[0.5, 0.0], [0.0, 0.0]]).requires_grad_()
    a = t([[0.0, 0.0], [1.0, 1.0]])
    loss, metrics = rebrac.actor_loss(q, pi, a, 0.1, normalize_q=True)
    # bc = (0.25, 2); lambda = 1 / mean |Q| = 1 / 3
    close(metrics["actor/bc_loss"], 1.125)
    close(metrics["actor/lambda"], 1.0 / 3.0)
    close(loss, ((0.1 * 0.25 - 2.0 / 3.0) + (0.1 * 2.0 + 4.0 / 3.0)) / 2)  # 0.445833...
    loss.backward()
    close(q.grad, [-1.0 / 6.0, -1.0 / 6.0])  # lambda held fixed
    close(pi.grad, [[0.1 * 2 * 0.5 / 2, 0.0], [0.1 * 2 * -1.0 / 2, 0.1 * 2 * -1.0 / 2]])
    loss, metrics = rebrac.actor_loss(q, pi, a, 0.1, normalize_q=False)
    close(loss, ((0.025 - 2.0) + (0.2 + 4.0)) / 2)  # lambda = 1: 1.1125
    close(metrics["actor/lambda"], 1.0)


def test_networks_have_layer_norm_in_the_critics_and_the_original_initialisation():
    c = rebrac.ReBRACConfig(**TINY)
    torch.manual_seed(0)
    actor, critics = rebrac.build_networks(LOWDIM_OBS, 3, c)
    assert not any(isinstance(m, nn.LayerNorm) for m in actor.modules())
    for q in (critics.q1, critics.q2):
        kinds = [type(m) for m in q]
        assert kinds == [nn.Linear, nn.ReLU, nn.LayerNorm] * 2 + [nn.Linear]
    for net, bound in ((actor.net, 1e-3), (critics.q1, 3e-3), (critics.q2, 3e-3)):
        linears = [m for m in net if isinstance(m, nn.Linear)]
        for hidden in linears[:-1]:
            assert torch.all(hidden.bias == 0.1)
            fan_in = hidden.weight.shape[1]
            assert hidden.weight.abs().max() <= 1.0 / np.sqrt(fan_in)
        last = linears[-1]
        assert last.weight.abs().max() <= bound and last.bias.abs().max() <= bound
        assert last.weight.abs().max() > bound / 10  # drawn, not zeros


def _params(module):
    return [p.detach().clone() for p in module.parameters()]


def test_the_target_actor_follows_the_actor_as_it_was_before_its_step():
    """As the original's ``optax.incremental_update(actor.params, ...)``: on an actor update
    the target actor moves towards the pre-step actor, the target critics towards the updated
    critics."""
    ag = make_agent("rebrac", LOWDIM_OBS, CONT_ACTION, tau=0.1, **TINY)
    data = [fake_transition(LOWDIM_OBS, CONT_ACTION, 6, i) for i in range(4)]
    actor0, critic0 = _params(ag.actor), _params(ag.critics)
    m = ag.update(data[0])
    assert not any(k.startswith("actor/") for k in m)
    m = ag.update(data[1])  # the actor's first step: its target moves towards actor0 itself
    assert "actor/loss" in m
    for got, old in zip(_params(ag.target_actor), actor0, strict=True):
        torch.testing.assert_close(got, old, rtol=0, atol=1e-7)
    for got, now, old in zip(_params(ag.target_critics), _params(ag.critics), critic0, strict=True):
        close(got, old + 0.1 * (now - old), 1e-7)
    actor2 = _params(ag.actor)
    assert not all(torch.equal(a, b) for a, b in zip(actor2, actor0, strict=True))
    ag.update(data[2])
    ag.update(data[3])  # towards the actor after update 2 (before update 4's step)
    for got, now, old in zip(_params(ag.target_actor), actor2, actor0, strict=True):
        close(got, old + 0.1 * (now - old), 1e-7)


def test_observation_normalisation_is_off_as_in_the_original_and_on_through_the_statistics():
    ag = make_agent("rebrac", LOWDIM_OBS, CONT_ACTION, **TINY)
    assert ag.batch_spec.statistics == () and ag.batch_spec.batch_size == 256  # small preset
    assert np.isfinite(ag.update(fake_transition(LOWDIM_OBS, CONT_ACTION, 6))["critic/loss"])
    on = make_agent("rebrac", LOWDIM_OBS, CONT_ACTION, normalize_observations=True, **TINY)
    assert on.batch_spec.statistics == ("observation",)
    with pytest.raises(RluError, match="rebrac normalises observations"):
        on.update(fake_transition(LOWDIM_OBS, CONT_ACTION, 6))
    mean = {k: np.full(s.shape, 3.0) for k, s in LOWDIM_OBS.items()}
    std = {k: np.full(s.shape, 2.0) for k, s in LOWDIM_OBS.items()}
    on.set_statistics(DataStatistics(observation_mean=mean, observation_std=std))
    obs = fake_transition(LOWDIM_OBS, CONT_ACTION, 4, seed=9).observation
    by_hand = {k: (v - 3.0) / (2.0 + 1e-3) for k, v in obs.items()}
    with torch.no_grad():
        raw = on.actor({k: torch.from_numpy(v.astype(np.float32)) for k, v in by_hand.items()})
    close(on.act(obs), on.scaler.from_unit(raw), 1e-6)
