"""Locomotion envs: the RLU builders, the rendered egocentric camera, spec and determinism."""

import numpy as np
import pytest

pytest.importorskip("dm_control")
pytest.importorskip("labmaze")

import rlu  # noqa: E402
from rlu.domains.envkit import check_observation, observation_space  # noqa: E402
from rlu.domains.locomotion.env import CAMERA_KEY  # noqa: E402
from rlu.tasks import list_tasks  # noqa: E402
from tests.envs.helpers import check_env_quietly, rollout, same  # noqa: E402

TASKS = [t.id for t in list_tasks("locomotion")]


@pytest.mark.parametrize("task_id", TASKS)
def test_builds_renders_the_camera_and_matches_the_spec(task_id):
    task = rlu.get_task(task_id)
    env = rlu.make_env(task_id, seed=0)
    assert env.observation_space == observation_space(task.observation_spec)
    assert env.action_space.shape == task.action_spec.shape
    obs, _ = env.reset()
    for _ in range(3):
        obs, r, term, trunc, _ = env.step(env.action_space.sample())
    check_observation(obs, task.observation_spec, task_id)
    img = obs[CAMERA_KEY]
    assert img.shape == (64, 64, 3) and img.dtype == np.uint8
    assert img.std() > 5 and len(np.unique(img)) > 20  # a rendered scene, not a constant
    env.close()


def test_camera_sees_the_walker_move():
    env = rlu.make_env("locomotion/rodent_gaps", seed=0)
    first = env.reset()[0][CAMERA_KEY]
    for _ in range(20):
        obs, *_ = env.step(env.action_space.sample())
    assert not np.array_equal(first, obs[CAMERA_KEY])


@pytest.mark.parametrize(
    "task_id",
    ["locomotion/rodent_gaps", "locomotion/rodent_two_touch", "locomotion/humanoid_walls"],
)
def test_same_seed_same_first_100_observations(task_id):
    # Without the camera for speed; the camera is a deterministic function of the state.
    a = rollout(rlu.make_env(task_id, camera=False), seed=4, steps=100)
    b = rollout(rlu.make_env(task_id, camera=False), seed=4, steps=100)
    assert all(same(x, y) for x, y in zip(a, b, strict=True))


def test_camera_is_deterministic_under_a_seed():
    a = rollout(rlu.make_env("locomotion/rodent_two_touch"), seed=1, steps=5)
    b = rollout(rlu.make_env("locomotion/rodent_two_touch"), seed=1, steps=5)
    assert all(same(x, y) for x, y in zip(a, b, strict=True))


def test_gymnasium_checker_and_actions_are_normalised():
    env = rlu.make_env("locomotion/rodent_gaps", seed=0, camera=False)
    check_env_quietly(env)
    raw = env.raw_env.action_spec()
    assert env.action_space.low.min() == -1 and env.action_space.high.max() == 1
    obs, _ = env.reset()
    env.step(np.ones(env.action_space.shape, np.float32))
    np.testing.assert_allclose(env.raw_env.env.physics.data.ctrl, raw.maximum, rtol=1e-6)
    assert CAMERA_KEY not in obs


def test_builders_use_the_original_parameters():
    env = rlu.make_env("locomotion/humanoid_gaps", seed=0, camera=False)
    task = env.raw_env.env.task
    assert task.physics_timestep == 0.005 and task.control_timestep == 0.03
    assert env.raw_env.env._time_limit == 30
    rodent = rlu.make_env("locomotion/rodent_bowl_escape", seed=0, camera=False).raw_env.env
    assert rodent.task.control_timestep == 0.02 and rodent._time_limit == 20
