"""Atari envs: Dopamine's preprocessing over the ALE, as the data was recorded."""

import numpy as np
import pytest

pytest.importorskip("ale_py")
pytest.importorskip("cv2")

import rlu  # noqa: E402
from rlu.domains.envkit import check_observation, observation_space  # noqa: E402
from rlu.envs import ATARI_ORIGINAL_EVAL_STEPS  # noqa: E402
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


@pytest.mark.parametrize("clip", [None, True, False])
def test_reward_is_the_raw_score_unless_clipping_is_asked_for(clip):
    settings = {} if clip is None else {"clip_rewards": clip}
    env = rlu.make_env("atari/Atlantis", seed=0, **settings)
    env.reset()
    for _ in range(2000):
        _, r, term, trunc, info = env.step(env.action_space.sample())
        if info["raw_reward"] > 1:
            assert r == (1.0 if clip else info["raw_reward"])
            return
    pytest.fail("no reward above 1 in 2000 steps of Atlantis")


def _plain_ale_returns(game, seeds, rng, num_actions, cap):
    """The oracle: ale_py's ALEInterface driven by hand with the paper's settings (sticky
    actions 0.25, each action repeated for 4 frames, minimal action set, game over ends the
    episode, ``cap`` agent steps at most), seeded as ale-py's own Gymnasium env seeds it
    (``SeedSequence(seed)``'s second word). Returns the raw game score of each episode and the
    largest raw reward of one agent step."""
    import ale_py

    returns, biggest = [], 0.0
    for seed in seeds:
        ale = ale_py.ALEInterface()
        ale.setLoggerMode(ale_py.LoggerMode.Error)
        ale.setFloat("repeat_action_probability", 0.25)
        _, ale_seed = np.random.SeedSequence(seed).generate_state(n_words=2)
        ale.setInt("random_seed", np.int32(ale_seed))
        ale.loadROM(ale_py.roms.get_rom_path(game))
        actions = ale.getMinimalActionSet()
        assert len(actions) == num_actions
        ale.reset_game()
        total = 0.0
        for _ in range(cap):
            a = actions[int(rng.integers(num_actions, size=1)[0])]
            step = 0.0
            for _ in range(4):
                step += ale.act(a)
                if ale.game_over():
                    break
            total += step
            biggest = max(biggest, step)
            if ale.game_over():
                break
        returns.append(total)
    return returns, biggest


def test_evaluation_scores_the_raw_game_score_of_a_plain_ale_loop():
    """Issue 18 item 1: what ``evaluate`` reports for Atari is the game's score. The same random
    policy (one seeded generator, one draw per step) scores exactly what a hand-written ALE loop
    scores with the same seeds; SpaceInvaders pays 5-30 points a hit, so a clipped sum differs."""
    from rlu.evaluation.rollout import episode_seed, evaluate, task_env_factory

    n, cap, seed, episodes = rlu.get_task("atari/SpaceInvaders").action_dim, 400, 11, 3
    rng = np.random.default_rng(7)

    def policy(obs, is_first, reward):
        return rng.integers(n, size=len(obs))

    factory = task_env_factory("atari/SpaceInvaders", max_episode_steps=cap)
    got = evaluate(policy, factory, num_episodes=episodes, seed=seed, num_envs=1)
    want, biggest = _plain_ale_returns(
        "space_invaders",
        [episode_seed(seed, i) for i in range(episodes)],
        np.random.default_rng(7),
        n,
        cap,
    )
    assert biggest > 1  # the oracle's episodes hold rewards that clipping would change
    assert list(got.returns) == want


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
