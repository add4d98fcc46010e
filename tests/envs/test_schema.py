"""An env episode written to the episode store and read back through the views is unchanged:
the env's observation spec is the dataset schema (frame stacking conventions included)."""

import numpy as np
import pytest

import rlu
from rlu.data.store import DatasetWriter, Schema, open_dataset
from rlu.data.views import TransitionView
from rlu.segments import make_episode


def _episode(env, steps):
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    observations, actions, rewards = [obs], [], []
    term = False
    for _ in range(steps):
        a = (
            env.action_space.sample()
            if not hasattr(env.action_space, "n")
            else int(rng.integers(env.action_space.n))
        )
        obs, r, term, trunc, _ = env.step(a)
        observations.append(obs), actions.append(a), rewards.append(r)
        if term or trunc:
            break
    return observations, np.asarray(actions), np.asarray(rewards), term


def _stack(observations):
    if isinstance(observations[0], dict):
        return {k: np.stack([o[k] for o in observations]) for k in observations[0]}
    return np.stack(observations)


@pytest.mark.parametrize(
    "task_id,challenge,module",
    [
        ("control_suite/walker_walk", "none", "dm_control"),
        ("rwrl/quadruped_walk", "easy", "dm_control"),
        ("locomotion/rodent_gaps", "none", "dm_control"),
    ],
)
def test_mujoco_episode_round_trips_through_the_store(tmp_path, task_id, challenge, module):
    pytest.importorskip(module)
    task = rlu.get_task(task_id)
    env = rlu.make_env(task_id, seed=0, challenge=challenge)
    observations, actions, rewards, term = _episode(env, 5)
    obs_spec = None
    if task.domain == "rwrl":
        obs_spec = rlu.tasks.rwrl_observation_spec(task, challenge)
    schema = Schema.for_task(task, observation=obs_spec)
    with DatasetWriter(tmp_path / "ds", schema) as w:
        w.append(make_episode(_stack(observations), actions.astype(np.float32), rewards, term))
    t = TransitionView(open_dataset(tmp_path / "ds")).all()
    for k in observations[0]:
        np.testing.assert_array_equal(t.observation[k], np.stack([o[k] for o in observations[:-1]]))
        np.testing.assert_array_equal(t.next_observation[k][-1], observations[-1][k])


def test_atari_frames_stacked_by_the_store_equal_the_env_stacks(tmp_path):
    pytest.importorskip("ale_py")
    task = rlu.get_task("atari/Pong")
    env = rlu.make_env(task.id, seed=0)
    observations, actions, rewards, term = _episode(env, 30)
    frames = np.stack([o[..., -1] for o in observations])
    prefix = np.zeros((3, 84, 84), np.uint8)  # zero frames before an episode start
    with DatasetWriter(tmp_path / "ds", Schema.for_task(task)) as w:
        w.append(make_episode(frames, actions.astype(np.int64), rewards, term, frame_prefix=prefix))
    t = TransitionView(open_dataset(tmp_path / "ds")).all()
    np.testing.assert_array_equal(t.observation, np.stack(observations[:-1]))
    np.testing.assert_array_equal(t.next_observation, np.stack(observations[1:]))
