"""Online / naive offline policy selection, Spearman and regret@1, FQE on a problem with known
values."""

from __future__ import annotations

import numpy as np
import pytest

from rlu.evaluation import protocols
from rlu.evaluation.fqe import FQEConfig, fqe_estimate
from rlu.types import BoundedSpec, RluError, Transition


def _records(table):
    return [
        {"task": t, "agent": a, "config": c, "seed": s, "score": v}
        for (t, a, c), seeds in table.items()
        for s, v in enumerate(seeds)
    ]


TABLE = {
    # online tasks
    ("on1", "bc", "lr=1"): [10.0, 12.0],  # mean 11
    ("on1", "bc", "lr=2"): [20.0, 22.0],  # mean 21
    ("on2", "bc", "lr=1"): [100.0, 100.0],  # mean 100
    ("on2", "bc", "lr=2"): [30.0, 34.0],  # mean 32
    ("on3", "bc", "lr=1"): [0.0, 2.0],  # mean 1
    ("on3", "bc", "lr=2"): [5.0, 7.0],  # mean 6
    # offline task
    ("off", "bc", "lr=1"): [1.0, 3.0],
    ("off", "bc", "lr=2"): [50.0, 60.0],
}


def test_online_selection_picks_best_mean_per_task():
    best = protocols.online_selection(_records(TABLE))
    assert best[("on1", "bc")].config == "lr=2"
    assert best[("on2", "bc")].config == "lr=1"
    assert best[("off", "bc")].config == "lr=2"
    sel = best[("on2", "bc")]
    assert sel.scores == (100.0, 100.0) and sel.mean == 100.0 and sel.std == 0.0
    assert best[("on1", "bc")].std == pytest.approx(2**0.5)  # 20, 22: the sample std
    one = protocols.Selection("t", "bc", "c", (5.0,), (0,))
    assert one.std is None  # one seed has no spread


def test_naive_offline_selection_mean_and_median():
    recs = _records(TABLE)
    # mean over online tasks: lr=1 -> (11+100+1)/3 = 37.3; lr=2 -> (21+32+6)/3 = 19.7
    chosen, res = protocols.offline_selection_naive(recs, ["on1", "on2", "on3"], ["off"], "mean")
    assert chosen == {"bc": "lr=1"}
    assert res[("off", "bc")].scores == (1.0, 3.0)
    # median over online tasks: lr=1 -> 11; lr=2 -> 21
    chosen, res = protocols.offline_selection_naive(recs, ["on1", "on2", "on3"], ["off"], "median")
    assert chosen == {"bc": "lr=2"}
    assert res[("off", "bc")].mean == 55.0


def test_naive_offline_selection_needs_every_online_task():
    recs = [r for r in _records(TABLE) if r["task"] != "on3"]
    with pytest.raises(RluError, match="every online-selection task"):
        protocols.offline_selection_naive(recs, ["on1", "on3"], ["off"])


def test_spearman_and_regret_hand_computed():
    scipy_stats = pytest.importorskip("scipy.stats")
    a, b = [1.0, 2.0, 3.0, 4.0], [10.0, 20.0, 40.0, 30.0]
    # rank differences 0 0 1 1 -> 1 - 6*2/(4*15) = 0.8
    assert protocols.spearman(a, b) == pytest.approx(0.8)
    x, y = [1.0, 1.0, 2.0, 5.0, 3.0], [2.0, 3.0, 3.0, 9.0, 1.0]  # with ties
    assert protocols.spearman(x, y) == pytest.approx(scipy_stats.spearmanr(x, y).statistic)
    sel = protocols.select_by_estimate(
        {"a": 5.0, "b": 9.0, "c": 1.0}, {"a": 100.0, "b": 80.0, "c": 0.0}
    )
    assert sel.chosen == "b"
    assert sel.regret_at_1 == pytest.approx(20.0)
    assert sel.normalized_regret_at_1 == pytest.approx(0.2)
    assert sel.spearman == pytest.approx(0.5)
    with pytest.raises(RluError, match="different candidates"):
        protocols.select_by_estimate({"a": 1.0}, {"b": 1.0})


def _quadratic_data(n_episodes=400, horizon=3, seed=0):
    """s_t ~ U(-1, 1) independent of actions, reward -(a - s)^2, episodes of ``horizon`` steps.
    The value of pi_k(s) = k s from a start state, with gamma = 1, is -horizon (k-1)^2 / 3."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(-1, 1, (n_episodes, horizon + 1)).astype(np.float32)
    a = rng.uniform(-1.5, 1.5, (n_episodes, horizon + 1)).astype(np.float32)
    r = -((a[:, :-1] - s[:, :-1]) ** 2)
    disc = np.ones((n_episodes, horizon), np.float32)
    disc[:, -1] = 0.0
    tr = Transition(
        observation={"s": s[:, :-1].reshape(-1, 1)},
        action=a[:, :-1].reshape(-1, 1),
        reward=r.reshape(-1),
        discount=disc.reshape(-1),
        next_observation={"s": s[:, 1:].reshape(-1, 1)},
        next_action=a[:, 1:].reshape(-1, 1),
    )
    return tr, {"s": s[:, 0].reshape(-1, 1)}


def test_fqe_ranks_policies_by_true_value():
    torch = pytest.importorskip("torch")
    torch.set_num_threads(1)  # tiny networks: threads only contend on a shared 2-core machine
    tr, init = _quadratic_data()
    spec = BoundedSpec((1,), "float32", -1.5, 1.5)
    ks = {"k=1": 1.0, "k=0.5": 0.5, "k=0": 0.0, "k=-0.5": -0.5}
    cfg = FQEConfig(gamma=1.0, steps=1000, hidden=(32, 32), target_period=50, learning_rate=3e-3)
    est = {
        name: fqe_estimate(tr, init, lambda o, first, reward, k=k: k * o["s"], spec, cfg)
        for name, k in ks.items()
    }
    true = {name: -3 * (k - 1) ** 2 / 3 for name, k in ks.items()}
    sel = protocols.select_by_estimate(est, true)
    assert sel.chosen == "k=1" and sel.regret_at_1 == 0.0
    assert sel.spearman == pytest.approx(1.0)
    for name in ks:  # close in value, not only in rank
        assert est[name] == pytest.approx(true[name], abs=0.5)
