"""Dopamine's online DQN (rlu.agents.dqn_online): exact numbers for its loss (no double Q) and
for TF1's centered RMSProp, worked out by hand from the formula; its preset against dqn.gin.

The loss only calls ``network(observation)``, so lookup tables indexed by integer
"observations" stand in for the networks (as in test_losses_discrete.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import discrete_common as dc  # noqa: E402
from rlu.agents import dqn_online, make_agent, make_config  # noqa: E402
from tests.fakes import ATARI_ACTION, ATARI_OBS, fake_transition  # noqa: E402

TINY = {"atari.channels": (4, 8, 8), "atari.hidden_size": 16}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def t(x, dtype=torch.float32):
    return torch.tensor(x, dtype=dtype)


def test_loss_bootstraps_from_the_target_networks_max_without_double_q():
    online = t([[1.0, 2.0], [0.0, 4.0], [3.0, 1.0]], torch.float64).requires_grad_(True)
    target = t([[0.0, 0.0], [8.0, 6.0], [2.0, 10.0]], torch.float64)
    batch = dc.TorchTransition(
        observation=t([0, 0, 2], torch.int64),
        action=t([1, 0, 1], torch.int64),
        reward=t([1.0, -1.0, 0.5], torch.float64),
        discount=t([1.0, 0.0, 1.0], torch.float64),
        next_observation=t([1, 2, 0], torch.int64),
    )
    loss, metrics = dqn_online.dopamine_dqn_loss(
        lambda s: online[s], lambda s: target[s], batch, 0.5, 1.0
    )
    # row 0: next s=1, max_a Q_target = 8 (the online argmax, action 1, would value it 6):
    #        y = 1 + 0.5 * 8 = 5; Q(0, 1) = 2; td 3 -> Huber 3 - 0.5 = 2.5
    # row 1: terminal: y = -1; Q(0, 0) = 1; td -2 -> 1.5
    # row 2: next s=0, max 0: y = 0.5; Q(2, 1) = 1; td -0.5 -> 0.5 * 0.25 = 0.125
    assert loss.item() == pytest.approx((2.5 + 1.5 + 0.125) / 3, rel=1e-12)
    assert metrics["critic/target"].item() == pytest.approx((5.0 - 1.0 + 0.5) / 3, rel=1e-12)
    assert metrics["critic/q"].item() == pytest.approx((2.0 + 1.0 + 1.0) / 3, rel=1e-12)
    loss.backward()
    # d loss / d Q(s, a) = -clip(td, -1, 1) / B on the taken entries only, none through y
    expected = np.zeros((3, 2))
    expected[0, 1] = -1.0 / 3
    expected[0, 0] = 1.0 / 3
    expected[2, 1] = 0.5 / 3
    np.testing.assert_allclose(online.grad.numpy(), expected, rtol=1e-12)


def tf_centered_rmsprop(w, g, ms, mg, mom, lr, rho, momentum, eps):
    """TF1's ApplyCenteredRMSProp, written out (tensorflow/python/training/rmsprop.py)."""
    ms = rho * ms + (1 - rho) * g * g
    mg = rho * mg + (1 - rho) * g
    mom = momentum * mom + lr * g / math.sqrt(ms - mg * mg + eps)
    return w - mom, ms, mg, mom


def test_one_rmsprop_step_is_tf1s_centered_formula_by_hand():
    w = torch.nn.Parameter(t([1.0, -2.0], torch.float64))
    opt = dqn_online.TFRMSProp([w], lr=0.1, decay=0.95, momentum=0.0, epsilon=1e-5, centered=True)
    w.grad = t([0.5, -3.0], torch.float64)
    opt.step()
    # TF1 starts ms at 1, mg at 0:
    # ms = 0.95 * 1 + 0.05 * 0.25 = 0.9625, 0.95 + 0.05 * 9 = 1.4; mg = 0.025, -0.15
    # w = 1 - 0.1 * 0.5 / sqrt(0.9625 - 0.025^2 + 1e-5), -2 + 0.1 * 3 / sqrt(1.4 - 0.15^2 + 1e-5)
    expected = [
        1.0 - 0.1 * 0.5 / math.sqrt(0.9625 - 0.000625 + 1e-5),
        -2.0 + 0.1 * 3.0 / math.sqrt(1.4 - 0.0225 + 1e-5),
    ]
    np.testing.assert_allclose(w.detach().numpy(), expected, rtol=1e-12)
    state = opt.state[w]
    np.testing.assert_allclose(state["rms"].numpy(), [0.9625, 1.4], rtol=1e-12)
    np.testing.assert_allclose(state["mg"].numpy(), [0.025, -0.15], rtol=1e-12)
    # torch's RMSprop (eps outside the root, ms from 0) moves w[0] by ~4.6 lr, not ~1 lr
    v = torch.nn.Parameter(t([1.0, -2.0], torch.float64))
    torch_opt = torch.optim.RMSprop([v], lr=0.1, alpha=0.95, eps=1e-5, centered=True)
    v.grad = t([0.5, -3.0], torch.float64)
    torch_opt.step()
    assert abs(v[0].item() - 1.0) > 4 * abs(w[0].item() - 1.0)


def test_rmsprop_carries_its_state_with_momentum_and_the_uncentered_form():
    for centered in (True, False):
        w = torch.nn.Parameter(t([0.3], torch.float64))
        opt = dqn_online.TFRMSProp([w], 0.01, 0.9, 0.5, 1e-3, centered)
        ref, ms, mg, mom = 0.3, 1.0, 0.0, 0.0
        for g in (2.0, -1.0, 0.25):
            w.grad = t([g], torch.float64)
            opt.step()
            if centered:
                ref, ms, mg, mom = tf_centered_rmsprop(ref, g, ms, mg, mom, 0.01, 0.9, 0.5, 1e-3)
            else:  # TF1's ApplyRMSProp: the same without mg
                ms = 0.9 * ms + 0.1 * g * g
                mom = 0.5 * mom + 0.01 * g / math.sqrt(ms + 1e-3)
                ref -= mom
            assert w.item() == pytest.approx(ref, rel=1e-12)


def test_paper_preset_is_dopamines_dqn_gin():
    c = make_config("dopamine_dqn", True, "paper")
    assert (c.learning_rate, c.rmsprop_decay, c.rmsprop_momentum, c.rmsprop_epsilon) == (
        0.00025, 0.95, 0.0, 0.00001,
    )  # fmt: skip
    assert c.centered is True
    a = c.atari
    assert (a.batch_size, a.gamma, a.n_step) == (32, 0.99, 1)
    assert (a.reward_clip, a.huber_delta) == (1.0, 1.0)
    assert (a.explore_epsilon, a.eval_epsilon) == (0.01, 0.001)
    assert a.target_update_period * 4 == 8000  # agent steps, one update per 4
    assert a.num_steps * 4 == 50_000_000
    assert (a.channels, a.kernel_sizes, a.strides, a.hidden_size) == (
        (32, 64, 64), (8, 4, 3), (4, 2, 1), 512,
    )  # fmt: skip
    assert make_config("dopamine_dqn", True, "small").atari.eval_epsilon == 0.001


def test_the_agents_update_is_the_loss_then_tf1s_rmsprop():
    agent = make_agent("dopamine_dqn", ATARI_OBS, ATARI_ACTION, preset="paper", **TINY)
    c = agent.config
    assert isinstance(agent.optimizers["network"], dqn_online.TFRMSProp)
    batch = fake_transition(ATARI_OBS, ATARI_ACTION, 6, seed=3)
    before = {k: p.detach().clone() for k, p in agent.network.named_parameters()}
    loss, _ = dqn_online.dopamine_dqn_loss(
        agent.network, agent.target_network, dc.to_torch(batch), 0.99, 1.0
    )
    grads = torch.autograd.grad(loss, list(agent.network.parameters()))
    grads = dict(zip(before, grads, strict=True))
    agent.update(batch)
    for k, p in agent.network.named_parameters():
        g = grads[k].double()
        ms = 0.95 + 0.05 * g * g
        mg = 0.05 * g
        step = c.learning_rate * g / torch.sqrt(ms - mg * mg + c.rmsprop_epsilon)
        np.testing.assert_allclose(p.detach(), before[k].double() - step, rtol=1e-5, atol=1e-9)
    # the target network is a hard copy every atari.target_update_period updates
    agent = make_agent("dopamine_dqn", ATARI_OBS, ATARI_ACTION, **TINY,
                       **{"atari.target_update_period": 2})  # fmt: skip
    first = [p.detach().clone() for p in agent.target_network.parameters()]
    agent.update(batch)
    assert all(
        torch.equal(a, b) for a, b in zip(first, agent.target_network.parameters(), strict=True)
    )
    agent.update(batch)
    assert all(
        torch.equal(a, b)
        for a, b in zip(agent.network.parameters(), agent.target_network.parameters(), strict=True)
    )
