"""Control suite envs: spec, Gymnasium contract, determinism, equality with raw dm_control."""

import numpy as np
import pytest

pytest.importorskip("dm_control")

import rlu  # noqa: E402
from rlu.domains.envkit import check_observation, observation_space  # noqa: E402
from rlu.tasks import list_tasks  # noqa: E402
from tests.envs.helpers import check_env_quietly, rollout, same  # noqa: E402

TASKS = [t.id for t in list_tasks("control_suite")]


@pytest.mark.parametrize("task_id", TASKS)
def test_contract_spec_and_determinism(task_id):
    task = rlu.get_task(task_id)
    env = rlu.make_env(task_id, seed=1)
    assert env.observation_space == observation_space(task.observation_spec)
    assert env.action_space.shape == task.action_spec.shape
    assert env.action_space.dtype == np.float32
    check_env_quietly(env)
    a = rollout(env, seed=7, steps=100)
    b = rollout(rlu.make_env(task_id, seed=99), seed=7, steps=100)
    assert all(same(x, y) for x, y in zip(a, b, strict=True))
    for obs in a[:3]:
        check_observation(obs, task.observation_spec, task_id)
    c = rollout(env, seed=8, steps=5)
    assert not same(a[1], c[1])


def test_matches_raw_dm_control():
    from dm_control import suite

    env = rlu.make_env("control_suite/walker_walk", seed=3)
    raw = suite.load("walker", "walk", task_kwargs={"random": 3})
    obs, _ = env.reset()
    ts = raw.reset()
    rng = np.random.default_rng(0)
    for _ in range(50):
        for k in obs:
            want = np.asarray(ts.observation[k], np.float32).reshape(obs[k].shape)
            np.testing.assert_array_equal(obs[k], want)
        a = rng.uniform(-1, 1, 6).astype(np.float32)
        obs, r, *_ = env.step(a)
        ts = raw.step(a)
        assert r == pytest.approx(ts.reward)
    assert obs["height"].shape == (1,)


def test_time_limit_truncates_and_seed_at_make_equals_seeded_reset():
    env = rlu.make_env("control_suite/cartpole_swingup", seed=5)
    first, _ = env.reset()
    again, _ = rlu.make_env("control_suite/cartpole_swingup").reset(seed=5)
    assert same(first, again)
    n, term, trunc = 0, False, False
    while not (term or trunc):
        _, _, term, trunc, info = env.step(np.zeros(1, np.float32))
        n += 1
    assert (n, term, trunc, info["discount"]) == (1000, False, True, 1.0)


def test_dm_env_view_matches_gym():
    env = rlu.make_env("control_suite/cheetah_run", seed=2)
    view = env.dm_env
    ts = view.reset()
    obs, _ = rlu.make_env("control_suite/cheetah_run", seed=2).reset()
    assert same(ts.observation, obs)
    assert ts.first()
    ts = view.step(np.zeros(6, np.float32))
    assert set(view.observation_spec()) == set(obs)
    assert view.action_spec().shape == (6,)
    assert ts.observation["position"].dtype == np.float32


def test_unknown_task_and_bad_setting_are_clear():
    with pytest.raises(rlu.types.RluError, match="unknown task id"):
        rlu.make_env("control_suite/cartpole_swingdown")
    with pytest.raises(rlu.types.RluError, match="unknown env settings"):
        rlu.make_env("control_suite/cartpole_swingup", camera=True)
    with pytest.raises(rlu.types.RluError, match="rwrl tasks only"):
        rlu.make_env("control_suite/cartpole_swingup", challenge="easy")
