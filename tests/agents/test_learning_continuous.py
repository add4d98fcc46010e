"""Learning checks (slow): every continuous agent's ``small`` preset on a small cartpole set.

The dataset is honest and recorded through rlu's own writer: a scripted energy-based swing-up
controller with a PD balancer, plus Gaussian action noise added in tanh space whose scale varies
by episode (0.3 to 1.5, so the data covers recoveries and failures), run on
``dm_control.suite.load("cartpole", "swingup")``, written with ``DatasetWriter`` and sampled
through ``rlu.data.views``. Each agent trains for a fixed number of updates on one thread (about
a minute of one core each, CQL two: its critics score 13 actions per state; several threads on a
busy machine are many times slower), then acts greedily in fresh environments. Bars: every agent
clearly beats the uniform random policy (3x its return); BC, over seeds 0-2, reaches 75 % of
the data's mean return on average. Run with ``-s`` to see the numbers.

BC's closed-loop return varies with the seed on this small set, the acting stream too (its
evaluation samples the mixture's component): at 3000 updates seeds 0-4 gave 458.9, 628.2, 480.5,
468.5 and 673.3 against a data mean of 622 (2026-12-04, each agent's random streams separated;
before, with acting seeded as the weights, seeds 0-3 gave 738, 606, 506 and 251), so one seed
cannot carry an 80 % bar and the check averages three. The later agents' returns vary with the
seed too and their checks use seed 0 (random: 43; measured with the earlier streams): CRR at 2000
updates 512, 455, 202 (seeds 0-2); IQL at 1000 updates 641, 520, 344; CQL at 2000 updates,
cloning for the first 500, 543, 314, 259 (at 1000, mostly cloning, 164).
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
suite = pytest.importorskip("dm_control.suite")

from rlu.agents import make_agent  # noqa: E402
from rlu.data import DatasetWriter, Schema, make_episode, open_dataset  # noqa: E402
from rlu.data.views import make_sampler  # noqa: E402
from rlu.tasks import get_task  # noqa: E402

TASK = "control_suite/cartpole_swingup"
NOISE = (0.3, 0.6, 1.0, 1.5)
NUM_EPISODES = 16
EVAL_EPISODES = 5
# Updates per agent with its small preset (sized to about a minute of one core per agent).
UPDATES = {"bc": 3000, "d4pg": 2000, "bcq": 1500, "brac": 4000, "rabm": 1500,
           "crr": 2000, "iql": 1000, "cql": 2000}  # fmt: skip
BC_SEEDS = (0, 1, 2)
SMALL_OVERRIDES = {"brac": {"behaviour_steps": 1000}, "cql": {"bc_steps": 500}}


def controller(obs: dict, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Energy pumping until the pole is near upright, then a PD balancer; plus noise."""
    x, c, s = obs["position"]
    xd, td = obs["velocity"]
    if c > 0.85:
        a = 10.0 * np.arctan2(s, c) + 2.0 * td + 1.0 * x + 1.5 * xd
    else:  # push with the pole's swing while its energy is short of upright's (0), brake past it
        energy = 0.5 * td**2 + 12.0 * (c - 1.0)
        a = np.sign(td * c) * np.clip(2.0 * energy, -1.0, 1.0) - 0.3 * x - 0.2 * xd
    # Noise in tanh space keeps actions strictly inside the box with a smooth density; noise added
    # after the fact and clipped would pile probability mass onto exactly -1 and 1.
    a = np.tanh(np.arctanh(np.clip(a, -0.95, 0.95)) + noise * rng.standard_normal())
    return np.array([a], np.float32)


def _obs(ts) -> dict:
    return {k: np.asarray(v, np.float32).reshape(-1) for k, v in ts.observation.items()}


def record(dest, num_episodes: int = NUM_EPISODES, seed: int = 0):
    task = get_task(TASK)
    rng = np.random.default_rng(seed)
    env = suite.load("cartpole", "swingup", task_kwargs={"random": seed})
    with DatasetWriter(dest, Schema.for_task(task), {"source": "scripted", "seed": seed}) as w:
        for i in range(num_episodes):
            noise = NOISE[i % len(NOISE)]
            ts = env.reset()
            obs, actions, rewards = [_obs(ts)], [], []
            while not ts.last():
                a = controller(obs[-1], noise, rng)
                ts = env.step(a)
                obs.append(_obs(ts))
                actions.append(a)
                rewards.append(ts.reward)
            stacked = {k: np.stack([o[k] for o in obs]) for k in obs[0]}
            w.append(make_episode(stacked, np.stack(actions), np.asarray(rewards, np.float32),
                                  terminal=False, metadata={"episode_id": i}))  # fmt: skip
    return open_dataset(dest)


def evaluate(policy, num_episodes: int = EVAL_EPISODES, seed: int = 100) -> float:
    """Mean return of ``policy`` (batched obs -> actions) over lock-stepped 1000-step episodes."""
    envs = [suite.load("cartpole", "swingup", task_kwargs={"random": seed + i})
            for i in range(num_episodes)]  # fmt: skip
    steps = [e.reset() for e in envs]
    returns = np.zeros(num_episodes)
    while not steps[0].last():
        obs = {k: np.stack([_obs(ts)[k] for ts in steps]) for k in steps[0].observation}
        actions = policy(obs)
        steps = [e.step(a) for e, a in zip(envs, actions, strict=True)]
        returns += [ts.reward for ts in steps]
    return float(returns.mean())


def train(name: str, ds, updates: int, seed: int = 0, **overrides):
    task = get_task(TASK)
    agent = make_agent(name, task.observation_spec, task.action_spec, preset="small", seed=seed,
                       **{**SMALL_OVERRIDES.get(name, {}), **overrides})  # fmt: skip
    sampler = make_sampler(ds, agent.batch_spec, seed=seed)
    for _ in range(updates):
        metrics = agent.update(sampler.sample())
    assert all(np.isfinite(v) for v in metrics.values()), metrics
    return agent


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield record(tmp_path_factory.mktemp("lc") / "cartpole_swingup")
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def random_return():
    rng = np.random.default_rng(0)
    return evaluate(lambda obs: rng.uniform(-1, 1, (len(obs["position"]), 1)).astype(np.float32))


@pytest.mark.slow
@pytest.mark.parametrize("name", list(UPDATES))
def test_small_preset_learns_cartpole_swingup(name, dataset, random_return):
    data_mean = float(np.mean(dataset.metadata("episode_return")))
    seeds = BC_SEEDS if name == "bc" else (0,)
    scores = [evaluate(train(name, dataset, UPDATES[name], seed=s).act) for s in seeds]
    print(f"\n{name}: returns {[round(x, 1) for x in scores]} (random {random_return:.1f}, "
          f"data mean {data_mean:.1f}, {UPDATES[name]} updates)")  # fmt: skip
    assert min(scores) > 3.0 * random_return
    if name == "bc":
        assert np.mean(scores) >= 0.75 * data_mean
