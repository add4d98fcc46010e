"""Every task is a Gymnasium id: gymnasium.make builds rlu's env, make_env sets the same spec."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

import rlu  # noqa: E402
import rlu.envs  # noqa: E402  (registers the ids)
from rlu.envs.registration import task_id_of  # noqa: E402
from rlu.types import RluError  # noqa: E402


def test_every_task_is_registered_under_one_namespace():
    ids = sorted(k for k in gym.registry if k.startswith("rlu/"))
    assert ids == sorted(t.gym_id for t in rlu.list_tasks())
    assert len(ids) == len(rlu.list_tasks()) == 74  # the paper's 66, bsuite's 3, DMLab's 5
    assert rlu.envs.gym_id("rwrl/walker_walk") == "rlu/rwrl-walker_walk-v0"
    for t in rlu.list_tasks():
        assert task_id_of(t.gym_id) == t.id
        spec = gym.spec(t.gym_id)
        assert spec.namespace == "rlu" and spec.kwargs == {"task_id": t.id}
    with pytest.raises(RluError, match="rlu/DOMAIN-NAME-v0"):
        task_id_of("ALE/Pong-v5")


def test_import_rlu_registers_nothing_and_imports_no_gymnasium():
    code = (
        "import sys, rlu; rlu.list_tasks(); print('gymnasium' in sys.modules); "
        "import gymnasium, rlu.envs; print(len([k for k in gymnasium.registry if "
        "k.startswith('rlu/')]))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "74"]


@pytest.mark.parametrize(
    "task_id,settings",
    [
        ("control_suite/cartpole_swingup", {}),
        ("atari/Pong", {"clip_rewards": False, "sticky_action_prob": 0.0}),
        ("rwrl/cartpole_swingup", {"challenge": "easy"}),
    ],
)
def test_gymnasium_make_equals_make_env(task_id, settings):
    pytest.importorskip("ale_py" if task_id.startswith("atari") else "dm_control")
    task = rlu.get_task(task_id)
    env = gym.make(task.gym_id, **settings)
    ours = rlu.make_env(task_id, **settings)
    assert env.unwrapped.spec.kwargs == {"task_id": task_id, **settings}
    assert ours.spec.id == task.gym_id and ours.spec.kwargs == {"task_id": task_id, **settings}
    assert env.observation_space == ours.observation_space
    assert env.action_space == ours.action_space
    a, _ = env.reset(seed=3)
    b, _ = ours.reset(seed=3)
    for _ in range(3):
        act = ours.action_space.sample()
        a, ra, *_ = env.step(act)
        b, rb, *_ = ours.step(act)
        assert ra == rb
    if isinstance(a, dict):
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    else:
        np.testing.assert_array_equal(a, b)
    # the spec makes the env again (what Minari's recover_environment does with a stored one)
    again = gym.make(gym.envs.registration.EnvSpec.from_json(ours.spec.to_json()))
    assert again.observation_space == ours.observation_space
    for e in (env, ours, again):
        e.close()


def test_make_env_spec_records_seed_and_challenge():
    pytest.importorskip("dm_control")
    env = rlu.make_env("rwrl/walker_walk", seed=5, challenge="easy")
    assert env.spec.kwargs == {"task_id": "rwrl/walker_walk", "seed": 5, "challenge": "easy"}
    assert str(env) == "<DmControlEnv<rlu/rwrl-walker_walk-v0>>"
    env.close()
