"""Learning check (slow): offline DQN, BCQ, REM, IQN and CQL beat BC where the data rewards it.

The task is a tiny corridor with the Atari observation: 84x84 uint8 frames, four stacked (newest
last, zeros before the start), three actions (0 no-op, 1 left, 2 right). The agent starts in the
middle of seven cells; the left end pays 0.1 and the right end 1.0, both terminal; episodes are
cut at 30 steps. The behaviour policy goes left more often than right (0.5 / 0.35, no-op 0.15),
so about a quarter of its episodes reach the 1.0 and most end on the 0.1: cloning it (its most
likely action is "left" everywhere) earns 0.1, while Q-learning from the same data finds "right"
(1.0). Right/left = 0.7 passes BCQ's 0.5 threshold, so BCQ may take it too.

The Q-learners use discount 0.9 here: with 0.99 a wasted no-op costs 1% of the value, less than
the approximation error after a thousand updates, and a greedy policy can loop on no-op forever.

CQL runs with alpha 0.1, not its preset's 1.0. The regulariser's gradient on Q(s, .) is
alpha (softmax Q(s, .) - pi_behaviour(. | s)): it pulls Q towards log pi_behaviour + const with
strength alpha, here a preference of up to log(0.5 / 0.35) = 0.36 for "left" in every cell,
against a true advantage of 0.15 for "right" at the start (0.9^2 = 0.81 vs 0.9^4 = 0.66). At
alpha 1 the pull wins and the greedy policy never reaches the 1.0 (measured: return 0.0-0.02
after 1000-1500 updates); at alpha 0.1 or 0.3 it does. Atari values, sums of many clipped
rewards, dwarf the same pull.

The data goes through the real store: episodes recorded with ``DatasetWriter`` (single frames,
``frame_stack=4``) and sampled with the transition sampler, which stacks the frames.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import make_agent  # noqa: E402
from rlu.data.store import DatasetWriter, Schema, open_dataset  # noqa: E402
from rlu.data.views import make_sampler, transition_sampler  # noqa: E402
from rlu.segments import make_episode  # noqa: E402
from rlu.types import ArraySpec, DiscreteSpec  # noqa: E402

CELLS, START, CAP = 7, 3, 30
LEFT_REWARD, RIGHT_REWARD = 0.1, 1.0
BEHAVIOUR = np.array([0.15, 0.5, 0.35])  # no-op, left, right
FRAME = ArraySpec((84, 84), "uint8")
OBS = ArraySpec((84, 84, 4), "uint8")
ACTION = DiscreteSpec((), "int64", 3)
STEPS = 1000
COMMON = {
    "atari.batch_size": 32,
    "atari.channels": (8, 16, 16),
    "atari.hidden_size": 64,
    "learning_rate": 3e-4,
}


def frame(cell: int) -> np.ndarray:
    image = np.zeros((84, 84), np.uint8)
    image[36:48, 2 + 11 * cell : 12 + 11 * cell] = 255
    return image


def env_step(cell: int, action: int) -> tuple[int, float, bool]:
    cell += {0: 0, 1: -1, 2: 1}[int(action)]
    if cell == 0:
        return cell, LEFT_REWARD, True
    if cell == CELLS - 1:
        return cell, RIGHT_REWARD, True
    return cell, 0.0, False


def record(path, episodes: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    schema = Schema(FRAME, ACTION, frame_stack=4)
    returns = []
    with DatasetWriter(path, schema, provenance={"source": "corridor behaviour policy"}) as w:
        for i in range(episodes):
            cell, cells, actions, rewards, terminal = START, [START], [], [], False
            while not terminal and len(actions) < CAP:
                action = int(rng.choice(3, p=BEHAVIOUR))
                cell, reward, terminal = env_step(cell, action)
                cells.append(cell)
                actions.append(action)
                rewards.append(reward)
            frames = np.stack([frame(c) for c in cells])
            w.append(
                make_episode(
                    frames,
                    np.array(actions, np.int64),
                    np.array(rewards, np.float32),
                    terminal,
                    metadata={"episode_id": i},
                )
            )
            returns.append(sum(rewards))
    return np.array(returns)


def evaluate(agent, episodes: int = 5) -> float:
    returns = []
    for _ in range(episodes):
        cell, total, terminal, steps = START, 0.0, False, 0
        stack = np.zeros((84, 84, 4), np.uint8)
        stack[..., -1] = frame(cell)
        while not terminal and steps < CAP:
            action = int(agent.act(stack[None])[0])
            cell, reward, terminal = env_step(cell, action)
            stack = np.concatenate([stack[..., 1:], frame(cell)[..., None]], axis=-1)
            total, steps = total + reward, steps + 1
        returns.append(total)
    return float(np.mean(returns))


@pytest.fixture
def one_thread():
    """One torch thread: on a shared 2-core machine two spinning threads fighting other
    processes run many times slower than one (and the numbers depend on the thread count)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("corridor") / "corridor"
    returns = record(path, episodes=300, seed=0)
    return open_dataset(path), returns


def test_the_stored_data_is_what_the_corridor_makes(dataset):
    ds, returns = dataset
    batch = transition_sampler(ds, 64, seed=0).sample()
    assert batch.observation.shape == (64, 84, 84, 4) and batch.observation.dtype == np.uint8
    # the newest frame shows one block; a step moves it by the action
    cells = (batch.observation[:, 40, 2::11, -1] == 255).argmax(1)
    next_cells = (batch.next_observation[:, 40, 2::11, -1] == 255).argmax(1)
    np.testing.assert_array_equal(next_cells - cells, np.array([0, -1, 1])[batch.action])
    assert 0.15 < np.mean(returns == RIGHT_REWARD) < 0.4  # the data does reward going right


@pytest.mark.slow
def test_offline_rl_beats_bc_where_the_data_rewards_it(dataset, one_thread):
    ds, returns = dataset
    scores = {}
    for name in ("bc", "dqn", "bcq", "rem", "iqn", "cql"):
        overrides = dict(COMMON)
        if name != "bc":
            overrides.update({"atari.target_update_period": 100, "atari.gamma": 0.9})
        if name == "cql":
            overrides["alpha"] = 0.1  # see the module docstring
        agent = make_agent(name, OBS, ACTION, "small", seed=0, **overrides)
        sampler = make_sampler(ds, agent.batch_spec, seed=1)
        for _ in range(STEPS):
            metrics = agent.update(sampler.sample())
        assert all(np.isfinite(v) for v in metrics.values())
        scores[name] = evaluate(agent)
    print(f"\ncorridor: behaviour mean return {returns.mean():.3f}; after {STEPS} updates {scores}")
    assert scores["bc"] <= LEFT_REWARD + 1e-6  # cloning the majority action goes left
    for name in ("dqn", "bcq", "rem", "iqn", "cql"):
        assert scores[name] > scores["bc"] + 0.5, scores
