"""Atari envs: Dopamine's preprocessing over the ALE, as the data was recorded."""

import numpy as np
import pytest

pytest.importorskip("ale_py")
pytest.importorskip("cv2")

import rlu  # noqa: E402
from rlu.envs import ATARI_ORIGINAL_EVAL_STEPS  # noqa: E402
from rlu.envs.core import check_observation, observation_space  # noqa: E402
from rlu.tasks import list_tasks  # noqa: E402
from tests.envs.helpers import check_env_quietly, rollout, same  # noqa: E402

GAMES = [t.id for t in list_tasks("atari")]


@pytest.mark.parametrize("task_id", GAMES)
def test_every_game_builds_with_the_spec_and_is_deterministic(task_id):
    task = rlu.get_task(task_id)
    env = rlu.make_env(task_id, seed=0)
    assert env.observation_space == observation_space(task.observation_spec)
    assert env.action_space.n == task.action_dim
    a = rollout(env, seed=5, steps=100)
    b = rollout(rlu.make_env(task_id), seed=5, steps=100)
    assert all(same(x, y) for x, y in zip(a, b, strict=True))
    check_observation(a[-1], task.observation_spec, task_id)


@pytest.mark.parametrize("task_id", ["atari/Pong", "atari/MsPacman", "atari/Seaquest"])
def test_gymnasium_checker(task_id):
    check_env_quietly(rlu.make_env(task_id, seed=0))


def test_zero_frames_before_the_first_and_newest_frame_last():
    env = rlu.make_env("atari/Breakout", seed=0)
    obs, _ = env.reset()
    assert obs.shape == (84, 84, 4) and obs.dtype == np.uint8
    assert not obs[..., :3].any() and obs[..., 3].any()
    nxt, *_ = env.step(0)
    np.testing.assert_array_equal(nxt[..., 2], obs[..., 3])
    assert not nxt[..., :2].any()
    for _ in range(3):
        last, *_ = env.step(0)
    assert last[..., 0].any()


def test_sticky_actions_frame_skip_and_pooling_match_the_ale():
    # Reproduce one agent step by hand on a second ALE with the same seed: 4 frames of the
    # sticky action, max of the last two grey screens, INTER_AREA resize to 84x84.
    import cv2

    env = rlu.make_env("atari/Pong", seed=3)
    ref = rlu.make_env("atari/Pong", seed=3)
    env.reset()
    ref.reset()
    ale = ref.unwrapped.ale
    actions = ref.unwrapped._actions
    rng = np.random.default_rng(0)
    for _ in range(50):
        a = int(rng.integers(6))
        obs, r, *_ = env.step(a)
        screens, reward = [], 0
        for _ in range(4):
            reward += ale.act(actions[a])
            screens.append(ale.getScreenGrayscale())
        frame = cv2.resize(
            np.maximum(screens[2], screens[3]), (84, 84), interpolation=cv2.INTER_AREA
        )
        np.testing.assert_array_equal(obs[..., -1], frame)
        assert r == reward
    assert ale.getFloat("repeat_action_probability") == pytest.approx(0.25)


@pytest.mark.parametrize("clip", [True, False])
def test_rewards_are_clipped_for_learning_and_raw_in_info(clip):
    env = rlu.make_env("atari/Atlantis", seed=0, clip_rewards=clip)
    env.reset()
    for _ in range(2000):
        _, r, term, trunc, info = env.step(env.action_space.sample())
        if info["raw_reward"] > 1:
            assert r == (1.0 if clip else info["raw_reward"])
            return
    pytest.fail("no reward above 1 in 2000 steps of Atlantis")


def test_episode_cap_in_agent_steps_and_the_original_setting():
    env = rlu.make_env("atari/Pong", seed=0, max_episode_steps=10)
    env.reset()
    flags = [env.step(0)[2:4] for _ in range(10)]
    assert flags[-1] == (False, True) and all(f == (False, False) for f in flags[:-1])
    assert rlu.make_env("atari/Pong").max_episode_steps == 27_000
    assert (
        rlu.make_env("atari/Pong", max_episode_steps=ATARI_ORIGINAL_EVAL_STEPS).max_episode_steps
        == 108_000
    )


def test_game_over_is_terminal():
    env = rlu.make_env("atari/Breakout", seed=0)
    env.reset()
    for _ in range(20000):
        _, _, term, trunc, info = env.step(env.action_space.sample())
        if term or trunc:
            break
    assert term and not trunc and info["lives"] == 0
