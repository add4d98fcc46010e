"""Discrete CQL as an agent: its paper preset, alpha 0 is double DQN to the bit, and the
regulariser lowers the values of the actions the data never took."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import agent_module, make_agent, make_config  # noqa: E402
from rlu.agents import discrete_common as dc  # noqa: E402
from tests.fakes import ATARI_ACTION, ATARI_OBS, fake_transition  # noqa: E402

TINY = {"atari.channels": (4, 8, 8), "atari.hidden_size": 16}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    # tiny networks: a second torch thread only fights the other processes (7x slower, measured)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_paper_preset_is_the_benchmark_table_with_the_authors_alpha_and_step_size():
    config = make_config("cql", True, "paper")
    assert config.atari == dc.AtariSettings()
    assert config.alpha == 1.0 and config.learning_rate == 5e-5
    assert config.learning_rate in dc.LEARNING_RATE_GRID
    assert config.double_q is True and config.atari.target_update_period == 2500
    assert agent_module("cql", True).GRID == {"learning_rate": [3e-5, 5e-5, 1e-4]}
    small = make_config("cql", True, "small")
    assert small.atari == dc.SMALL and small.alpha == 1.0
    assert small.atari.target_update_period == dc.SMALL.target_update_period


def test_alpha_zero_trains_exactly_like_dqn():
    cql = make_agent("cql", ATARI_OBS, ATARI_ACTION, "small", seed=3, alpha=0.0, **TINY)
    dqn = make_agent("dqn", ATARI_OBS, ATARI_ACTION, "small", seed=3, **TINY)
    same = {k: v for k, v in dataclasses.asdict(cql.config).items() if k != "alpha"}
    assert same == dataclasses.asdict(dqn.config)  # every other setting matches
    for i in range(3):
        batch = fake_transition(ATARI_OBS, ATARI_ACTION, batch=8, seed=i)
        a, b = cql.update(batch), dqn.update(batch)
        assert a["critic/loss"] == b["critic/loss"] == a["critic/td_loss"]
    for (name, p), q in zip(cql.network.state_dict().items(), dqn.network.state_dict().values(),
                            strict=True):  # fmt: skip
        assert torch.equal(p, q), name


def gap(agent, observation: np.ndarray) -> float:
    """Mean over states of max over the unlogged actions of Q, minus Q of the logged action 0."""
    with torch.no_grad():
        q = agent.network(torch.from_numpy(observation))
    return float((q[:, 1:].max(-1).values - q[:, 0]).mean())


def test_the_regulariser_pushes_unlogged_actions_below_the_logged_one():
    # Every logged action is 0: with no rewards the TD loss says nothing about actions 1..5, so
    # DQN leaves them where initialisation put them; CQL pushes them under Q(s, 0).
    batch = fake_transition(ATARI_OBS, ATARI_ACTION, batch=16, seed=0)
    batch = batch._replace(action=np.zeros_like(batch.action), reward=np.zeros_like(batch.reward))
    gaps = {}
    for alpha in (0.0, 1.0):
        agent = make_agent(
            "cql", ATARI_OBS, ATARI_ACTION, "small", seed=0, alpha=alpha, learning_rate=1e-3,
            **TINY,
        )  # fmt: skip
        for _ in range(30):
            metrics = agent.update(batch)
        gaps[alpha] = gap(agent, batch.observation)
        penalty = metrics["critic/conservative_penalty"]
    assert gaps[1.0] < -0.5 and gaps[1.0] < gaps[0.0] - 0.5, gaps
    assert penalty < np.log(6.0)  # below its value for equal Q over the six actions
