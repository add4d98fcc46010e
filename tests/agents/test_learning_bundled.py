"""Learning checks (long) of TD3+BC and ReBRAC on the bundled control_suite/cartpole_swingup
data (40 episodes made by ``rlu generate``, mean return 500.2), through the training loop, so
the dataset statistics reach the agents as in every run: each ``small`` preset for its 20,000
updates, one torch thread, then 10 greedy episodes in dm_control's cartpole swingup. Run with
``-s`` to see the numbers.

ReBRAC (seed 0): the return beats BC's (its small preset, trained the same way here) or the
data's mean. Measured on the bundled data as regenerated on 2026-12-02: BC 112.6, ReBRAC 482.3
(2026-12-04, each agent's random streams separated); with the streams before (learner noise
seeded as the weights) BC 347.1, ReBRAC 356.9.

TD3+BC does not beat BC on this data (then: 206.8, 287.0, 171.2 over seeds 0-2), so a bar on its
return against BC's cannot tell a broken TD3+BC from a working one. Its check is on what TD3+BC
must get right whatever the data: its critic. Over seeds 0-2 the first critic's values along the
greedy policy's own episodes must correlate with their exact discounted returns at 0.6 or more,
average at least a fifth of them (TD3's minimum of two critics underestimates, more so 20,000
updates in), and the policy must return 4 times the random policy's 23.3. Measured 2026-12-04
(``td3bc_checks``): working, seeds 0-2, correlation 0.73, 0.74, 0.85, ratio 0.39, 0.32, 0.36,
return 170.2, 227.9, 446.2; broken on purpose, seed 0: the reward's sign flipped in the target
-0.84 and -0.39 (fails), the target without its bootstrap (r alone) 0.44 and 0.01 (fails). Two
actor-side breakages pass, and the check says so rather than hides it: an actor loss without its
Q term (BC alone: 0.81, 0.35, return 271.7) and one that descends Q (0.79, 0.35, 255.3). On this
data and budget the Q term moves the policy too little for any return to show it (the actor's
Q(s, pi(s)) - Q(s, a) on data states is 0.08-0.10 % of |Q| working, 0.08-0.09 % with
either breakage); the actor's loss is pinned instead by the exact-number tests
(``test_losses_td3bc.py``) and by ``bench/td3bc_updates.py``, update for update against d3rlpy's
TD3PlusBC.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("dm_control")

TASK = "control_suite/cartpole_swingup"
EPISODES = 10


def small_preset_return(name: str, folder) -> float:
    from rlu.data.bundled import bundled_dataset
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
    from rlu.data.bundled import bundled_dataset

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
    from rlu.data.bundled import bundled_dataset
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
    return {
        "return": score,
        "critic_corr": float(np.corrcoef(q, g)[0, 1]),
        "critic_ratio": float(q.mean() / g.mean()),
    }


@pytest.mark.slow
@pytest.mark.long  # outside CI: RLU_SLOW=2
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_td3bc_critic_predicts_its_policys_returns_on_the_bundled_cartpole(seed, tmp_path):
    """The bars (module docstring: working seeds against broken variants, measured): the first
    critic's values along the policy's own episodes correlate with their discounted returns at
    0.6 or more and are on average at least a fifth of them (TD3's minimum of two critics
    underestimates, more so before the targets converge), and the policy returns at least 4
    times the uniform random policy's 23.3."""
    r = td3bc_checks(seed, tmp_path / "run")
    print(f"\ntd3bc seed {seed}: {r}")
    assert r["critic_corr"] >= 0.6, r
    assert r["critic_ratio"] >= 0.2, r
    assert r["return"] >= 4 * 23.3, r
