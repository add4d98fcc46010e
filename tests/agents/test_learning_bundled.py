"""Learning checks (long) of TD3+BC and ReBRAC on the bundled control_suite/cartpole_swingup
data (40 episodes made by ``rlu generate``, mean return 500.2), through the training loop, so
the dataset statistics reach the agents as in every run: each ``small`` preset for its 20,000
updates, seed 0, one torch thread, then 10 greedy episodes in dm_control's cartpole swingup.
Bar: the return beats BC's (its small preset, trained the same way here) or the data's mean.
About half an hour of one core for the three runs; run with ``-s`` to see the numbers.

Measured on the bundled data as regenerated on 2026-12-02 (docs/agents.md, "Learning on the
bundled data"): BC 347.1; ReBRAC 356.9 (passes); TD3+BC 206.8, and with seeds 1 and 2 287.0 and
171.2: on this data TD3+BC's 20,000 updates stay below BC's return and the data's mean (on the
earlier bytes, mean 435.6, they gave 286.7, 437.9, 266.7 against BC's 130). Its case is a strict
xfail: it says so until TD3+BC passes, and then fails so that the mark is removed.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("dm_control")

TASK = "control_suite/cartpole_swingup"
EPISODES = 10


def small_preset_return(name: str, folder) -> float:
    from rlu.generate.recipe import bundled_dataset
    from rlu.training.train import train
    from tests.fakes import train_config

    cfg = train_config(
        task=TASK, agent=name, dataset=str(bundled_dataset(TASK)), preset="small", seed=0,
        eval_every=0, eval_episodes=EPISODES, torch_threads=1, log_every=1000,
    )  # fmt: skip
    return float(train(cfg, folder / name, progress=False)["score"])


@pytest.fixture(scope="module")
def bars(tmp_path_factory):
    from rlu.data import open_dataset
    from rlu.generate.recipe import bundled_dataset

    data_mean = float(np.mean(open_dataset(bundled_dataset(TASK)).episode_returns()))
    return small_preset_return("bc", tmp_path_factory.mktemp("bc")), data_mean


@pytest.mark.slow
@pytest.mark.long  # outside CI: RLU_SLOW=2
def test_rebrac_small_preset_beats_bc_or_the_data_on_the_bundled_cartpole(bars, tmp_path):
    bc, data_mean = bars
    score = small_preset_return("rebrac", tmp_path)
    print(f"\nrebrac: return {score:.1f} (bc {bc:.1f}, data mean {data_mean:.1f})")
    assert score > bc or score > data_mean


GAMMA = 0.99
HORIZON = 500  # states t < 500 of a 1000-step episode: the discounted tail past 1000 < 0.7 %


def td3bc_checks(seed: int, folder) -> dict[str, float]:
    """TD3+BC's small preset trained through the loop (20,000 updates), then three figures:
    how well its first critic predicts its own policy's discounted return along greedy
    episodes in the environment (correlation and mean ratio over every state t < 500 of two
    episodes: exact Monte Carlo returns, the env and the policy being deterministic), how far
    its actor climbs that critic above the data's actions on data states (Q_1(s, pi(s)) -
    Q_1(s, a) on 4,096 of them, in units of the data's mean |Q_1(s, a)|), and its return."""
    import torch

    import rlu
    from rlu.agents import common
    from rlu.data import open_dataset, transition_sampler
    from rlu.generate.recipe import bundled_dataset
    from rlu.training.restore import load_agent
    from rlu.training.train import train
    from tests.fakes import train_config

    cfg = train_config(
        task=TASK, agent="td3bc", dataset=str(bundled_dataset(TASK)), preset="small", seed=seed,
        eval_every=0, eval_episodes=EPISODES, torch_threads=1, log_every=1000,
    )  # fmt: skip
    score = float(train(cfg, folder, progress=False)["score"])
    agent, _ = load_agent(folder)

    def q1(observation, action=None):
        with torch.no_grad():
            obs = agent.critics.encoder.flatten(
                agent.normaliser(common.to_torch(observation, agent.device))
            )
            a = agent.actor(obs) if action is None else agent.scaler.to_unit(action)
            return agent.critics.first(obs, a).numpy().astype(np.float64)

    predicted, actual = [], []
    for episode in range(2):
        env = rlu.make_env(TASK, seed=1000 * (seed + 1) + episode)
        obs, _ = env.reset()
        observations, rewards, done = [], [], False
        while not done:
            observations.append(obs)
            action = agent.act({k: v[None] for k, v in obs.items()})[0]
            obs, reward, terminated, truncated, _ = env.step(action)
            rewards.append(float(reward))
            done = terminated or truncated
        env.close()
        returns = np.zeros(len(rewards) + 1)
        for t in range(len(rewards) - 1, -1, -1):
            returns[t] = rewards[t] + GAMMA * returns[t + 1]
        stacked = {k: np.stack([o[k] for o in observations[:HORIZON]]) for k in obs}
        predicted.append(q1(stacked))
        actual.append(returns[:HORIZON])
    q, g = np.concatenate(predicted), np.concatenate(actual)
    batch = transition_sampler(open_dataset(bundled_dataset(TASK)), 4096, seed=seed).sample()
    q_data = q1(batch.observation, torch.as_tensor(batch.action))
    q_pi = q1(batch.observation)
    return {
        "return": score,
        "critic_corr": float(np.corrcoef(q, g)[0, 1]),
        "critic_ratio": float(q.mean() / g.mean()),
        "actor_gain": float((q_pi - q_data).mean() / np.abs(q_data).mean()),
    }
