"""CRR's advantage, weights and losses on tiny hand-computed inputs (exact numbers)."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import crr, make_agent  # noqa: E402
from rlu.types import RluError  # noqa: E402
from tests.fakes import CONT_ACTION, LOWDIM_OBS, fake_transition  # noqa: E402


def t(x):
    return torch.tensor(x, dtype=torch.float32)


def close(a, b, tol=1e-6):
    a, b = (x.detach() if isinstance(x, torch.Tensor) else x for x in (a, b))
    np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), atol=tol)


def test_advantage_subtracts_the_mean_or_the_max_over_policy_samples():
    q = t([3.0, 1.0])
    samples = t([[1.0, 4.0], [3.0, 0.0]])  # (m=2, B=2)
    close(crr.advantage(q, samples, "mean"), [3.0 - 2.0, 1.0 - 2.0])
    close(crr.advantage(q, samples, "max"), [3.0 - 3.0, 1.0 - 4.0])


def test_exp_weights_are_capped_and_binary_weights_need_a_strictly_positive_advantage():
    adv = t([1.0, -1.0, 4.0])
    close(crr.crr_weights(adv, "exp", beta=2.0, ratio_upper_bound=2.0),
          [math.exp(0.5), math.exp(-0.5), 2.0])  # fmt: skip
    close(crr.crr_weights(t([1.0, 0.0, -1.0]), "binary", 1.0, 20.0), [1.0, 0.0, 0.0])


def test_policy_loss_is_the_weighted_negative_log_likelihood_with_fixed_weights():
    log_prob = t([-1.0, -2.0]).requires_grad_()
    weights = t([2.0, 0.5]).requires_grad_()
    loss, metrics = crr.policy_loss(log_prob, weights, t([0.3, -0.1]))
    close(loss, -(2.0 * -1.0 + 0.5 * -2.0) / 2)  # 1.5
    close(metrics["actor/weight_mean"], 1.25)
    close(metrics["actor/advantage_mean"], 0.1)
    loss.backward()
    close(log_prob.grad, [-1.0, -0.25])  # -w / B
    assert weights.grad is None  # the critic's verdict is not trained through the policy loss


def test_critic_loss_is_cross_entropy_to_the_shifted_and_projected_target():
    atoms = t([0.0, 1.0, 2.0])
    logits = torch.log(t([[0.25, 0.5, 0.25], [0.25, 0.5, 0.25]]))
    next_probs = t([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])  # all mass at 1 in s'
    # Row 0: 0.5 + 0.5 * 1 = 1 -> atom 1. Row 1 is terminal: every atom -> 0.5, split 0 / 1.
    loss, metrics = crr.critic_loss(logits, next_probs, t([0.5, 0.5]), t([1.0, 0.0]), atoms, 0.5)
    row0 = -math.log(0.5)
    row1 = -(0.5 * math.log(0.25) + 0.5 * math.log(0.5))
    close(loss, (row0 + row1) / 2)
    close(metrics["critic/q_mean"], 1.0)


def test_unknown_variants_are_refused_with_the_field_named():
    with pytest.raises(RluError, match="advantage_weight"):
        make_agent("crr", LOWDIM_OBS, CONT_ACTION, advantage_weight="linear")
    with pytest.raises(RluError, match="baseline"):
        make_agent("crr", LOWDIM_OBS, CONT_ACTION, baseline="median")


def test_binary_variant_with_no_better_action_leaves_the_policy_alone():
    # With the critic's weights zeroed, Q is the same for every action: A = 0 everywhere, so
    # binary weights are all 0 and the policy takes no step; the exp variant still clones.
    for kind, moves in (("binary", False), ("exp", True)):
        agent = make_agent("crr", LOWDIM_OBS, CONT_ACTION, hidden_size=16, num_layers=2,
                           advantage_weight=kind, baseline="max")  # fmt: skip
        with torch.no_grad():
            agent.critic.head.linear.weight.zero_()
        before = [p.detach().clone() for p in agent.policy.parameters()]
        metrics = agent.update(fake_transition(LOWDIM_OBS, CONT_ACTION, 8))
        after = list(agent.policy.parameters())
        changed = any(not torch.equal(a, b) for a, b in zip(before, after, strict=True))
        assert changed is moves, kind
        close(metrics["actor/advantage_mean"], 0.0, 1e-5)


def test_targets_are_copied_every_period():
    agent = make_agent("crr", LOWDIM_OBS, CONT_ACTION, hidden_size=16, num_layers=2,
                       target_update_period=2)  # fmt: skip

    def same() -> bool:
        pairs = zip(agent.critic.parameters(), agent.target_critic.parameters(), strict=True)
        return all(torch.equal(a, b) for a, b in pairs)

    batch = fake_transition(LOWDIM_OBS, CONT_ACTION, 8)
    agent.update(batch)
    assert not same()
    agent.update(batch)
    assert same()
