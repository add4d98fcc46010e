"""Vector envs: sub-envs equal the single envs; the ALE backend has the same preprocessing."""

import numpy as np
import pytest

import rlu  # noqa: E402
from tests.envs.helpers import same  # noqa: E402


@pytest.mark.parametrize("backend,n", [("process", 3), ("async", 2)])
def test_sub_envs_are_the_single_envs_of_seed_plus_i(backend, n):
    pytest.importorskip("dm_control")
    from rlu.envs import make_vector_env

    tid = "control_suite/cartpole_swingup"
    venv = make_vector_env(
        tid, num_envs=n, seed=10, backend=backend, num_workers=2 if backend == "process" else None
    )
    singles = [rlu.make_env(tid, seed=10 + i) for i in range(n)]
    try:
        obs, _ = venv.reset()
        want = [e.reset()[0] for e in singles]
        rng = np.random.default_rng(0)
        for _ in range(20):
            for i in range(n):
                assert same({k: v[i] for k, v in obs.items()}, want[i])
            a = rng.uniform(-1, 1, (n, 1)).astype(np.float32)
            obs, r, term, trunc, _ = venv.step(a)
            steps = [e.step(a[i]) for i, e in enumerate(singles)]
            want = [s[0] for s in steps]
            np.testing.assert_allclose(r, [s[1] for s in steps], rtol=1e-6)
    finally:
        venv.close()


def test_ale_vector_env_frames_equal_the_single_env():
    pytest.importorskip("ale_py")
    pytest.importorskip("cv2")
    from rlu.domains.atari.env import AleVectorEnv, AtariEnv

    # Without sticky actions both envs are deterministic given the actions, so the frames
    # (pooling, resize, stacking, zero padding) must be bit-identical.
    venv = AleVectorEnv("MsPacman", 1, seed=0, sticky_action_prob=0.0, clip_rewards=False)
    env = AtariEnv("MsPacman", 0, sticky_action_prob=0.0, clip_rewards=False)
    obs, _ = venv.reset()
    ref, _ = env.reset()
    assert obs.shape == (1, 84, 84, 4)
    np.testing.assert_array_equal(obs[0], ref)
    rng = np.random.default_rng(0)
    for _ in range(200):
        a = int(rng.integers(env.action_space.n))
        obs, r, term, trunc, info = venv.step(np.array([a]))
        ref, r1, term1, trunc1, info1 = env.step(a)
        np.testing.assert_array_equal(obs[0], ref)
        assert r[0] == r1 and term[0] == term1
    venv.close()


def test_auto_backend_per_domain():
    pytest.importorskip("dm_control")
    import gymnasium as gym

    from rlu.envs import make_vector_env

    venv = make_vector_env("rwrl/cartpole_swingup", num_envs=2, seed=0, challenge="easy")
    assert isinstance(venv, gym.vector.SyncVectorEnv)
    obs, _ = venv.reset()
    assert obs["dummy-0"].shape == (2, 1)
    venv.close()


def test_default_backends_and_batch_shapes():
    pytest.importorskip("ale_py")
    from rlu.domains.atari.env import AleVectorEnv
    from rlu.envs import make_vector_env

    venv = make_vector_env("atari/Pong", num_envs=2, seed=0)
    assert isinstance(venv, AleVectorEnv)
    obs, _ = venv.reset()
    assert obs.shape == (2, 84, 84, 4) and obs.dtype == np.uint8
    obs, r, term, trunc, info = venv.step(np.zeros(2, np.int64))
    assert r.shape == (2,) and info["raw_reward"].shape == (2,)
    venv.close()
    with pytest.raises(rlu.types.RluError, match="backend"):
        make_vector_env("atari/Pong", num_envs=2, backend="threads")


def test_process_backend_autoresets_on_the_next_step():
    pytest.importorskip("ale_py")
    from rlu.envs import make_vector_env

    venv = make_vector_env("atari/Pong", num_envs=2, seed=0, backend="process", max_episode_steps=3)
    try:
        obs, _ = venv.reset()
        for _ in range(3):
            obs, r, term, trunc, info = venv.step(np.zeros(2, np.int64))
        assert trunc.all() and not term.any() and obs[:, :, :, 0].any()
        obs, r, term, trunc, info = venv.step(np.zeros(2, np.int64))
        assert not obs[:, :, :, :3].any() and (r == 0).all() and not trunc.any()
    finally:
        venv.close()


@pytest.mark.parametrize("clip", [False, True])
def test_ale_vector_env_returns_raw_scores_unless_clipping_is_asked_for(clip):
    pytest.importorskip("ale_py")
    from rlu.envs import make_vector_env

    settings = {"clip_rewards": True} if clip else {}  # the default is the raw score
    venv = make_vector_env("atari/SpaceInvaders", num_envs=2, seed=0, **settings)
    rng = np.random.default_rng(0)
    try:
        venv.reset()
        for _ in range(2000):
            _, r, _, _, info = venv.step(rng.integers(6, size=2))
            raw = info["raw_reward"]
            if (raw > 1).any():
                np.testing.assert_array_equal(r, np.clip(raw, -1, 1) if clip else raw)
                return
    finally:
        venv.close()
    pytest.fail("no reward above 1 in 2000 steps of SpaceInvaders")
