"""Vectorised rollouts on a real Gymnasium env: returns independent of the number of envs, the
policy sees batched observations only, clear errors."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from rlu.evaluation.rollout import episode_seed, evaluate, task_env_factory
from rlu.types import RluError

pytest.importorskip("gymnasium")


def _factory():
    return task_env_factory("test/pendulum", "tests.train.pendulum:make_env")


def _pd_policy(seen):
    def policy(obs, is_first, reward):
        seen.append(obs)
        th = np.arctan2(obs["orientation"][:, 1], obs["orientation"][:, 0])
        return np.clip(-(6.0 * th + 1.5 * obs["velocity"][:, 0]), -2, 2)[:, None].astype(np.float32)

    return policy


def test_returns_do_not_depend_on_num_envs():
    seen: list = []
    one = evaluate(_pd_policy(seen), _factory(), num_episodes=5, seed=3, num_envs=1)
    three = evaluate(_pd_policy([]), _factory(), num_episodes=5, seed=3, num_envs=3)
    assert one.returns == three.returns
    assert one.lengths == (50,) * 5
    assert len(set(one.returns)) == 5  # episode i is seeded with episode_seed(3, i)
    # batched dict observations, nothing else
    assert all(set(o) == {"orientation", "velocity"} for o in seen)
    assert {o["orientation"].shape for o in seen} == {(1, 2)}
    # no episode of seed 4 replays one of seed 3 (under seed + i, four of five did)
    other_seed = evaluate(_pd_policy([]), _factory(), num_episodes=5, seed=4, num_envs=2)
    assert not set(other_seed.returns) & set(one.returns)
    seeds = {episode_seed(s, i) for s in range(50) for i in range(50)}
    assert len(seeds) == 2500


def test_max_steps_and_errors(monkeypatch):
    res = evaluate(_pd_policy([]), _factory(), num_episodes=2, seed=0, num_envs=2, max_steps=7)
    assert res.lengths == (7, 7)
    assert res.to_json()["mean"] == pytest.approx(np.mean(res.returns))
    with pytest.raises(RluError, match="at least one episode"):
        evaluate(_pd_policy([]), _factory(), num_episodes=0)
    with pytest.raises(RluError, match="module:function"):
        task_env_factory("x", "no_colon")
    with pytest.raises(RluError, match="cannot be imported"):
        task_env_factory("x", "no_such_module_xyz:make_env")
    monkeypatch.setitem(sys.modules, "rlu.envs", None)  # as if rlu.envs were not installed
    with pytest.raises(RluError, match="rlu.envs cannot be imported"):
        task_env_factory("control_suite/cartpole_swingup")


def test_a_torch_policy_runs_in_inference_mode():
    torch = pytest.importorskip("torch")
    modes = []

    def policy(obs, is_first, reward):
        modes.append(torch.is_inference_mode_enabled())
        return np.zeros((len(obs["velocity"]), 1), np.float32)

    evaluate(policy, _factory(), num_episodes=2, seed=0, num_envs=2, max_steps=3)
    assert modes == [True] * 3 and not torch.is_inference_mode_enabled()


def test_every_call_has_one_row_per_env_and_marks_episode_starts():
    """Recurrent policies keep a state per row: rows never move between envs, and ``is_first``
    marks the step each episode starts on (an env with no episode left keeps its row)."""
    calls = []

    def policy(obs, is_first, reward):
        calls.append((obs["velocity"].shape[0], is_first.tolist()))
        return np.zeros((len(is_first), 1), np.float32)

    res = evaluate(policy, _factory(), num_episodes=3, seed=0, num_envs=2, max_steps=4)
    assert res.lengths == (4, 4, 4)
    assert {rows for rows, _ in calls} == {2}
    firsts = [f for _, f in calls]
    # episodes 0 and 1 start together; episode 2 starts on env 0 when episode 0 ends
    assert firsts == [[True, True], [False, False], [False, False], [False, False],
                      [True, False], [False, False], [False, False], [False, False]]  # fmt: skip


def test_every_call_gets_the_reward_of_each_rows_previous_action():
    """The rollout hands every policy what each row's previous action earned (0 where an
    episode starts), so a return-conditioned policy can lower its return to go; the rewards the
    policy is given add up to the returns the evaluation reports."""
    calls = []

    def policy(obs, is_first, reward):
        calls.append((is_first.copy(), reward.copy()))
        th = np.arctan2(obs["orientation"][:, 1], obs["orientation"][:, 0])
        return np.clip(-(6.0 * th + 1.5 * obs["velocity"][:, 0]), -2, 2)[:, None].astype(np.float32)

    res = evaluate(policy, _factory(), num_episodes=3, seed=0, num_envs=2, max_steps=4)
    firsts = np.array([f for f, _ in calls])
    rewards = np.array([r for _, r in calls])
    assert rewards.dtype == np.float64 and (rewards[firsts] == 0).all()
    assert (rewards[~firsts] != 0).all()  # the pendulum pays a nonzero reward every step
    # env 0 runs episodes 0 then 2 (4 steps each), env 1 episode 1: the rewards of steps 1-3
    # arrive at the next three calls; step 4's is never needed by the policy
    assert rewards[1:4, 0].sum() == pytest.approx(res.returns[0] - _last_reward(0, res))
    assert rewards[5:8, 0].sum() == pytest.approx(res.returns[2] - _last_reward(2, res))


def _last_reward(episode: int, res) -> float:
    """The reward of an episode's last step, replayed with the same seeds and actions."""
    from rlu.evaluation.rollout import episode_seed

    env = _factory()()
    obs, _ = env.reset(seed=episode_seed(0, episode))
    r = 0.0
    for _ in range(res.lengths[episode]):
        th = np.arctan2(obs["orientation"][1], obs["orientation"][0])
        a = np.clip(-(6.0 * th + 1.5 * obs["velocity"][0]), -2, 2).astype(np.float32)
        obs, r, *_ = env.step(np.array([a], np.float32))
    env.close()
    return float(r)
