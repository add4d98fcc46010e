"""Exact numbers for the discrete targets and losses on tiny hand-computed inputs (Dopamine's way).

Each agent's loss only calls ``network(observation)``, so a lookup table indexed by integer
"observations" stands in for the network and every number below is worked out by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import bc_discrete, bcq_discrete, cql_discrete, dqn, iqn, rem  # noqa: E402
from rlu.agents import discrete_common as dc  # noqa: E402


def t(x, dtype=torch.float32):
    return torch.tensor(x, dtype=dtype)


def transition(obs, action, reward, discount, next_obs):
    return dc.TorchTransition(
        observation=t(obs, torch.int64),
        action=t(action, torch.int64),
        reward=t(reward),
        discount=t(discount),
        next_observation=t(next_obs, torch.int64),
    )


def test_huber():
    x = t([-2.0, -0.5, 0.0, 0.5, 2.0])
    np.testing.assert_allclose(dc.huber(x, 1.0), [1.5, 0.125, 0.0, 0.125, 1.5])
    np.testing.assert_allclose(dc.huber(x, 2.0), [2.0, 0.125, 0.0, 0.125, 2.0])


def test_double_q_target_selects_online_and_values_target():
    q_next_online = t([[1.0, 3.0], [2.0, 0.0]])
    q_next_target = t([[10.0, 20.0], [30.0, 40.0]])
    reward, discount = t([1.0, 0.0]), t([1.0, 1.0])
    # online argmax = [1, 0] -> target values [20, 30]; a max target would give [20, 40]
    y = dc.double_q_target(reward, discount, 0.5, q_next_online, q_next_target)
    np.testing.assert_allclose(y, [11.0, 15.0])
    np.testing.assert_allclose(
        dc.q_learning_target(reward, discount, 0.5, q_next_target), [11.0, 20.0]
    )
    # discount 0 (terminal) cuts the bootstrap
    y = dc.double_q_target(reward, t([0.0, 0.0]), 0.5, q_next_online, q_next_target)
    np.testing.assert_allclose(y, [1.0, 0.0])


def test_double_q_loss_end_to_end():
    online = t([[1.0, 2.0], [0.0, 4.0], [3.0, 1.0]])  # Q(s, a) for s = 0, 1, 2
    target = t([[0.0, 0.0], [8.0, 6.0], [2.0, 10.0]])
    batch = transition([0, 0], [1, 0], [1.0, -1.0], [1.0, 0.0], [1, 2])
    loss, metrics = dqn.dqn_loss(lambda s: online[s], lambda s: target[s], batch, 0.5, 1.0, True)
    # row 0: next s=1, online argmax 1 -> target 6 -> y = 1 + 0.5*6 = 4; Q(0,1)=2; td 2 -> 1.5
    # row 1: terminal -> y = -1; Q(0,0)=1; td -2 -> 1.5
    assert loss.item() == pytest.approx(1.5)
    assert metrics["critic/target"].item() == pytest.approx(1.5)
    assert metrics["critic/q"].item() == pytest.approx(1.5)
    # without double-Q, row 0 bootstraps from max target 8 -> y = 5, td 3 -> 2.5
    loss, _ = dqn.dqn_loss(lambda s: online[s], lambda s: target[s], batch, 0.5, 1.0, False)
    assert loss.item() == pytest.approx((2.5 + 1.5) / 2)


def test_cql_penalty_is_logsumexp_minus_the_logged_q_and_pushes_on_every_action():
    q = t([[1.0, 2.0], [1.0, 2.0], [0.0, math.log(3.0)]]).requires_grad_(True)
    action = t([1, 0, 0], torch.int64)
    penalty = cql_discrete.conservative_penalty(q, action)
    # log(e + e^2) = 2 + log(1 + 1/e); rows: log(1 + 1/e), 1 + log(1 + 1/e); log(1 + 3) - 0
    soft = math.log(1.0 + math.exp(-1.0))
    assert penalty.item() == pytest.approx((soft + (1.0 + soft) + math.log(4.0)) / 3, rel=1e-6)
    # d/dQ: (softmax(Q) - onehot(a_data)) / B -- down on every action by its soft-max weight,
    # up on the logged one: no stop-gradient, no target network
    penalty.backward()
    p1 = 1.0 / (1.0 + math.exp(-1.0))  # softmax of [1, 2] at action 1
    expected = [[1 - p1, p1 - 1], [(1 - p1) - 1, p1], [0.25 - 1, 0.75]]
    np.testing.assert_allclose(q.grad.numpy(), np.array(expected) / 3, rtol=1e-6)


def test_cql_loss_is_the_dqn_loss_plus_alpha_times_the_penalty():
    online = t([[1.0, 2.0], [0.0, 4.0], [3.0, 1.0]])  # Q(s, a) for s = 0, 1, 2
    target = t([[0.0, 0.0], [8.0, 6.0], [2.0, 10.0]])
    batch = transition([0, 0], [1, 0], [1.0, -1.0], [1.0, 0.0], [1, 2])
    loss, metrics = cql_discrete.cql_loss(
        lambda s: online[s], lambda s: target[s], batch, 0.5, alpha=2.0
    )
    # TD part as in test_double_q_loss_end_to_end: 1.5. Penalty at s=0 (Q = [1, 2]): row 0 took
    # action 1 -> log(1 + 1/e); row 1 took action 0 -> 1 + log(1 + 1/e).
    penalty = math.log(1.0 + math.exp(-1.0)) + 0.5
    assert metrics["critic/td_loss"].item() == pytest.approx(1.5)
    assert metrics["critic/conservative_penalty"].item() == pytest.approx(penalty, rel=1e-6)
    assert loss.item() == pytest.approx(1.5 + 2.0 * penalty, rel=1e-6)
    assert metrics["critic/loss"].item() == pytest.approx(loss.item())
    assert metrics["critic/target"].item() == pytest.approx(1.5)  # targets 4 and -1
    # the authors' target (the target network's own argmax): row 0 bootstraps from 8 -> y = 5
    _, m = cql_discrete.cql_loss(
        lambda s: online[s], lambda s: target[s], batch, 0.5, alpha=2.0, double_q=False
    )
    assert m["critic/td_loss"].item() == pytest.approx((2.5 + 1.5) / 2)
    # alpha 0 is DQN's loss, with either target
    for double_q in (True, False):
        zero, _ = cql_discrete.cql_loss(
            lambda s: online[s], lambda s: target[s], batch, 0.5, 0.0, double_q=double_q
        )
        plain, _ = dqn.dqn_loss(
            lambda s: online[s], lambda s: target[s], batch, 0.5, double_q=double_q
        )
        assert zero.item() == plain.item()


def test_quantile_huber_loss():
    quantiles, taus = t([[0.0, 1.0]]), t([[0.25, 0.75]])
    # one target 2: u = [2, 1]; weights |tau - 0| -> 0.25*1.5 + 0.75*0.5
    np.testing.assert_allclose(iqn.quantile_huber_loss(quantiles, taus, t([[2.0]])), [0.75])
    # targets [2, -1]: u_0 = [2, -1], u_1 = [1, -2]
    # i=0: (0.25*1.5 + 0.75*0.5)/2 = 0.375; i=1: (0.75*0.5 + 0.25*1.5)/2 = 0.375
    np.testing.assert_allclose(iqn.quantile_huber_loss(quantiles, taus, t([[2.0, -1.0]])), [0.75])
    # kappa 2: huber(u, 2)/2 = [1, .25] and [.25, 1]
    # i=0: (0.25*1 + 0.75*0.25)/2; i=1: (0.75*0.25 + 0.25*1)/2
    got = iqn.quantile_huber_loss(quantiles, taus, t([[2.0, -1.0]]), kappa=2.0)
    np.testing.assert_allclose(got, [0.4375])
    # kappa 0: plain quantile regression, |tau - 1{u<0}| |u|
    got = iqn.quantile_huber_loss(t([[0.0]]), t([[0.1]]), t([[3.0, -2.0]]), kappa=0.0)
    np.testing.assert_allclose(got, [(0.1 * 3 + 0.9 * 2) / 2])


def test_quantile_huber_gradient_pushes_toward_the_tau_quantile():
    # With many targets, the minimiser of the loss is the tau-quantile of the targets.
    targets = torch.arange(101, dtype=torch.float32)[None]  # 0..100
    q = torch.zeros(1, 1, requires_grad=True)
    opt = torch.optim.SGD([q], lr=50.0)
    for _ in range(400):
        opt.zero_grad()
        iqn.quantile_huber_loss(q, t([[0.3]]), targets, kappa=0.0).sum().backward()
        opt.step()
    assert q.item() == pytest.approx(30.0, abs=1.0)


def test_cosine_tau_embedding():
    emb = iqn.cosine_tau_embedding(t([[0.0, 0.5, 1.0]]), 3)
    assert emb.shape == (1, 3, 3)
    np.testing.assert_allclose(emb[0], [[1, 1, 1], [1, 0, -1], [1, -1, 1]], atol=1e-6)
    tau = 0.3
    np.testing.assert_allclose(
        iqn.cosine_tau_embedding(t([tau]), 4)[0],
        [math.cos(math.pi * i * tau) for i in range(4)],
        rtol=1e-6,
    )


def test_quantile_loss_end_to_end_matches_a_loop():
    # Z(s, tau, a) = base[s, a] + scale[a] * tau, a stand-in "network" linear in tau
    base = t([[0.0, 1.0], [2.0, -1.0], [0.5, 0.5]])
    scale = t([1.0, 3.0])

    def network(s, taus):
        return base[s][:, None, :] + taus[..., None] * scale

    batch = transition([0, 1], [1, 0], [1.0, 0.5], [1.0, 0.0], [1, 2])
    generator = torch.Generator().manual_seed(0)
    replay = torch.Generator().manual_seed(0)
    loss, _ = iqn.iqn_loss(network, network, batch, 0.9, generator, 3, 2)

    taus = torch.rand(2, 3, generator=replay).numpy()
    taus_next = torch.rand(2, 2, generator=replay).numpy()
    b, s = base.numpy(), scale.numpy()
    expected = []
    for k, (obs, a, r, d, nxt) in enumerate([(0, 1, 1.0, 1.0, 1), (1, 0, 0.5, 0.0, 2)]):
        next_z = b[nxt][None, :] + taus_next[k][:, None] * s[None, :]  # (N', A)
        best = next_z.mean(0).argmax()
        targets = r + 0.9 * d * next_z[:, best]
        total = 0.0
        for i in range(3):
            z = b[obs, a] + s[a] * taus[k, i]
            terms = []
            for y in targets:
                u = y - z
                h = 0.5 * u * u if abs(u) <= 1 else abs(u) - 0.5
                terms.append(abs(taus[k, i] - (u < 0)) * h)
            total += np.mean(terms)
        expected.append(total)
    assert loss.item() == pytest.approx(np.mean(expected), rel=1e-5)


def test_random_convex_weights_sum_to_one_and_are_resampled():
    generator = torch.Generator().manual_seed(0)
    first = rem.random_convex_weights(4, generator)
    second = rem.random_convex_weights(4, generator)
    for w in (first, second):
        assert w.shape == (4,) and bool((w >= 0).all())
        assert w.sum().item() == pytest.approx(1.0, abs=1e-6)
    assert not torch.allclose(first, second)


def test_rem_loss_uses_one_convex_combination_per_batch():
    # heads (K=2) x actions (A=2) per state
    online = t([[[1.0, 2.0], [3.0, 0.0]], [[0.0, 0.0], [0.0, 0.0]], [[4.0, 0.0], [0.0, 8.0]]])
    target = online * 2
    batch = transition([0, 0], [0, 1], [0.0, 1.0], [1.0, 1.0], [2, 1])
    generator = torch.Generator().manual_seed(1)
    replay = torch.Generator().manual_seed(1)

    def loss_fn(online_fn, target_fn, batch):
        alpha = rem.random_convex_weights(2, generator)
        return rem.rem_loss(online_fn, target_fn, batch, 0.5, alpha)

    loss, _ = loss_fn(lambda s: online[s], lambda s: target[s], batch)
    alpha = rem.random_convex_weights(2, replay)
    a0, a1 = alpha.tolist()
    q = [a0 * 1 + a1 * 3, a0 * 2 + a1 * 0]  # state 0, actions 0 / 1
    next_state2 = max(a0 * 8 + a1 * 0, a0 * 0 + a1 * 16)
    y = [0.0 + 0.5 * next_state2, 1.0 + 0.5 * 0.0]
    td = [y[0] - q[0], y[1] - q[1]]
    expected = np.mean([dc.huber(torch.tensor(x)).item() for x in td])
    assert loss.item() == pytest.approx(expected, rel=1e-6)
    # the next batch draws a new combination, so the same batch gives another loss
    loss2, _ = loss_fn(lambda s: online[s], lambda s: target[s], batch)
    assert loss2.item() != pytest.approx(loss.item())


def test_rem_paper_preset_is_an_ensemble_of_four_separate_networks():
    from rlu.agents import make_agent
    from tests.fakes import ATARI_ACTION, ATARI_OBS, fake_transition

    tiny = {"atari.channels": (4, 8, 8), "atari.hidden_size": 16, "atari.batch_size": 8}
    agent = make_agent("rem", ATARI_OBS, ATARI_ACTION, preset="paper", **tiny)
    assert make_agent("rem", ATARI_OBS, ATARI_ACTION, **tiny).config.separate_networks is False
    ensemble = agent.network
    assert isinstance(ensemble, rem.QEnsemble) and len(ensemble.networks) == 4
    frames = dc.frames(fake_transition(ATARI_OBS, ATARI_ACTION, 3).observation)
    out = ensemble(frames)
    assert out.shape == (3, 4, ATARI_ACTION.num_values)
    for k, network in enumerate(ensemble.networks):  # estimate k is network k's own output
        torch.testing.assert_close(out[:, k], network(frames))
    first = [net.torso.convs[0].weight.detach().clone() for net in ensemble.networks]
    assert all(not torch.equal(first[0], w) for w in first[1:])  # initialised apart
    for seed in range(2):  # every network learns: each carries a share of alpha
        agent.update(fake_transition(ATARI_OBS, ATARI_ACTION, 8, seed))
    for w, net in zip(first, ensemble.networks, strict=True):
        assert not torch.equal(w, net.torso.convs[0].weight)


def test_bcq_action_mask():
    logits = torch.log(t([[0.6, 0.25, 0.15]]))  # ratios to the max: 1, 0.4167, 0.25
    assert bcq_discrete.bcq_action_mask(logits, 0.0).tolist() == [[True, True, True]]
    assert bcq_discrete.bcq_action_mask(logits, 0.4).tolist() == [[True, True, False]]
    assert bcq_discrete.bcq_action_mask(logits, 0.5).tolist() == [[True, False, False]]
    assert bcq_discrete.bcq_action_mask(logits, 1.0).tolist() == [[True, False, False]]
    # ties at the max all pass threshold 1; tiny probabilities (log-space) pass threshold 0
    assert bcq_discrete.bcq_action_mask(t([[1.0, 1.0, 0.0]]), 1.0).tolist() == [[True, True, False]]
    assert bcq_discrete.bcq_action_mask(t([[0.0, -1e4]]), 0.0).tolist() == [[True, True]]


def _bcq_tables():
    q = t([[1.0, 2.0, 0.0], [0.0, 5.0, 4.0]])  # Q(s, a), s = 0, 1
    q_target = t([[0.0, 0.0, 0.0], [7.0, 1.0, 3.0]])
    # behaviour at s=1 prefers action 2 (prob .7), then 0 (.2), then 1 (.1)
    logits = torch.log(t([[0.2, 0.5, 0.3], [0.2, 0.1, 0.7]]))
    batch = transition([0], [1], [1.0], [1.0], [1])
    return q, q_target, logits, batch


def test_bcq_threshold_zero_is_double_dqn_and_one_is_the_behaviour_argmax():
    q, q_target, logits, batch = _bcq_tables()

    def online(s):
        return q[s], logits[s]

    def target(s):
        return q_target[s], logits[s]

    bcq0, m0 = bcq_discrete.bcq_loss(online, target, batch, 0.5, threshold=0.0, logit_penalty=0.0)
    dqn_value, md = dqn.dqn_loss(lambda s: q[s], lambda s: q_target[s], batch, 0.5)
    # online argmax at s=1 is action 1 -> target value 1 -> y = 1.5; Q(0, 1) = 2; td -0.5
    assert md["critic/target"].item() == pytest.approx(1.5)
    assert m0["critic/loss"].item() == pytest.approx(dqn_value.item()) == pytest.approx(0.125)
    assert m0["critic/target"].item() == pytest.approx(md["critic/target"].item())
    bc = -math.log(0.5)  # cross-entropy of action 1 at s=0
    assert m0["actor/bc_loss"].item() == pytest.approx(bc, rel=1e-6)
    assert bcq0.item() == pytest.approx(0.125 + bc, rel=1e-6)

    # threshold 1: only the behaviour argmax (action 2) is allowed -> target 3 -> y = 2.5, td 0.5
    _, m1 = bcq_discrete.bcq_loss(online, target, batch, 0.5, threshold=1.0)
    assert m1["critic/target"].item() == pytest.approx(2.5)
    assert m1["critic/loss"].item() == pytest.approx(0.125)
    # threshold 0.25: actions 2 and 0 pass (0.2/0.7 = 0.29) -> online argmax among them is 2
    _, m = bcq_discrete.bcq_loss(online, target, batch, 0.5, threshold=0.25)
    assert m["critic/target"].item() == pytest.approx(2.5)
    # the logit penalty adds 1e-2 * mean(logits^2)
    total, _ = bcq_discrete.bcq_loss(online, target, batch, 0.5, threshold=1.0, logit_penalty=1e-2)
    penalty = 1e-2 * (logits[0] ** 2).mean().item()
    assert total.item() == pytest.approx(0.125 + bc + penalty, rel=1e-6)


def test_bc_loss():
    logits = torch.log(t([[0.5, 0.25, 0.25], [0.1, 0.8, 0.1]]))
    batch = transition([0, 1], [1, 1], [0.0, 0.0], [1.0, 1.0], [0, 1])
    loss, metrics = bc_discrete.bc_loss(logits[batch.observation], batch.action)
    assert loss.item() == pytest.approx((-math.log(0.25) - math.log(0.8)) / 2, rel=1e-6)
    assert metrics["actor/accuracy"].item() == pytest.approx(0.5)


def test_epsilon_greedy():
    scores = t([[0.0, 1.0, 0.5]]).expand(10_000, 3)
    generator = torch.Generator().manual_seed(0)
    assert (dc.epsilon_greedy(scores, 0.0, generator) == 1).all()
    actions = dc.epsilon_greedy(scores, 0.3, generator)
    # argmax with prob 0.7 + 0.3/3
    assert np.mean(actions == 1) == pytest.approx(0.8, abs=0.02)
    assert np.mean(actions == 0) == pytest.approx(0.1, abs=0.02)
    assert dc.EVAL_EPSILON == pytest.approx(6.5536e-4)
