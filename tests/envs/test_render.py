"""Envs you can watch: rgb_array frames on every domain, the real time limit in the spec, and a
close() that can be called twice. All on the real envs (dm_control, ALE)."""

from __future__ import annotations

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

import rlu  # noqa: E402
import rlu.envs  # noqa: E402  (registers the ids)
from rlu.types import RluError  # noqa: E402
from tests.envs.helpers import same  # noqa: E402

# One task per domain, with settings that keep them cheap; (height, width) of their frames.
DOMAINS = [
    ("control_suite/cartpole_swingup", {}, (480, 640)),
    ("rwrl/walker_walk", {"challenge": "easy"}, (480, 640)),
    ("locomotion/rodent_gaps", {"camera": False}, (480, 640)),
    ("atari/Pong", {}, (210, 160)),
]


def _need(task_id: str) -> None:
    pytest.importorskip("ale_py" if task_id.startswith("atari") else "dm_control")
    if task_id.startswith("locomotion"):
        pytest.importorskip("labmaze")


def _act(env, rng):
    space = env.action_space
    if hasattr(space, "n"):
        return int(rng.integers(space.n))
    return rng.uniform(-1, 1, space.shape).astype(np.float32)


@pytest.mark.parametrize("task_id,settings,hw", DOMAINS)
def test_rgb_array_frames_show_the_scene_moving(task_id, settings, hw):
    _need(task_id)
    env = rlu.make_env(task_id, seed=0, render_mode="rgb_array", **settings)
    assert env.render_mode == "rgb_array" and "rgb_array" in env.metadata["render_modes"]
    assert env.metadata["render_fps"] > 0
    rng = np.random.default_rng(0)
    env.reset(seed=1)
    first = env.render()
    assert first.shape == (*hw, 3) and first.dtype == np.uint8
    colours = len(np.unique(first.reshape(-1, 3), axis=0))
    assert first.std() > 5 and colours >= 4  # a drawn scene, not a blank buffer (Pong has ~8)
    for _ in range(15 if task_id.startswith("atari") else 30):
        env.step(_act(env, rng))
    assert not np.array_equal(first, env.render())  # the body, cart or ball moved
    env.close()


@pytest.mark.parametrize("task_id,settings,hw", DOMAINS)
def test_gymnasium_make_renders_and_records_the_mode_in_the_spec(task_id, settings, hw):
    _need(task_id)
    task = rlu.get_task(task_id)
    env = gym.make(task.gym_id, render_mode="rgb_array", **settings)
    assert env.render_mode == "rgb_array"
    env.reset(seed=0)
    assert env.render().shape == (*hw, 3)
    assert env.spec.kwargs["render_mode"] == "rgb_array"
    ours = rlu.make_env(task_id, render_mode="rgb_array", **settings)
    assert ours.spec.kwargs == env.spec.kwargs
    again = gym.make(gym.envs.registration.EnvSpec.from_json(ours.spec.to_json()))
    again.reset(seed=0)
    assert again.render().shape == (*hw, 3)
    for e in (env, ours, again):
        e.close()


def test_gymnasium_checker_passes_with_its_render_checks():
    pytest.importorskip("dm_control")
    import warnings

    from gymnasium.utils.env_checker import check_env

    env = rlu.make_env("control_suite/cartpole_swingup", seed=0, render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # about unbounded feature Boxes, expected
        # makes the env again from env.spec in each render mode and checks render()'s output
        check_env(env, skip_render_check=False)
    env.close()


def test_rendering_leaves_observations_alone():
    """A seeded rollout with frames drawn around every step sees the very observations of one
    without (the locomotion egocentric camera shares the GL context with the render view)."""
    _need("locomotion/rodent_two_touch")

    def run(draw: bool) -> list:
        env = rlu.make_env("locomotion/rodent_two_touch", render_mode="rgb_array")
        rng = np.random.default_rng(0)
        out = [env.reset(seed=2)[0]]
        for _ in range(5):
            if draw:
                env.render()
            out.append(env.step(_act(env, rng))[0])
        env.close()
        return out

    assert all(same(a, b) for a, b in zip(run(False), run(True), strict=True))


def test_render_camera_and_size_choose_the_view():
    _need("control_suite/walker_walk")
    side = rlu.make_env("control_suite/walker_walk", seed=0, render_mode="rgb_array")
    back = rlu.make_env(
        "control_suite/walker_walk",
        seed=0,
        render_mode="rgb_array",
        render_camera="back",
        render_size=(120, 160),
    )
    side.reset(seed=0)
    back.reset(seed=0)
    assert side.render().shape == (480, 640, 3)
    small = back.render()
    assert small.shape == (120, 160, 3)
    same_view = rlu.make_env(
        "control_suite/walker_walk", seed=0, render_mode="rgb_array", render_size=(120, 160)
    )
    same_view.reset(seed=0)
    assert not np.array_equal(same_view.render(), small)  # camera 0 ('side') is another view
    for e in (side, back, same_view):
        e.close()


def test_bad_render_settings_are_refused_with_the_fix():
    _need("control_suite/cartpole_swingup")
    _need("atari/Pong")
    task = "control_suite/cartpole_swingup"
    with pytest.raises(RluError, match="render_mode='human' is not offered"):
        rlu.make_env(task, render_mode="human")
    with pytest.raises(RluError, match=r"no camera 'nope'; the model has \['fixed', 'lookatcart"):
        rlu.make_env(task, render_mode="rgb_array", render_camera="nope")
    with pytest.raises(RluError, match="exceeds the model's offscreen framebuffer"):
        rlu.make_env(task, render_mode="rgb_array", render_size=(2000, 2000))
    with pytest.raises(RluError, match="need render_mode='rgb_array'"):
        rlu.make_env(task, render_camera="fixed")
    with pytest.raises(RluError, match="Atari renders the ALE's own"):
        rlu.make_env("atari/Pong", render_mode="rgb_array", render_size=(100, 100))
    with pytest.raises(RluError, match="render_mode='human' is not offered"):
        gym.make("rlu/control_suite-cartpole_swingup-v0", render_mode="human")
    for task_id in (task, "atari/Pong"):
        env = rlu.make_env(task_id)
        env.reset(seed=0)
        with pytest.raises(RluError, match="render\\(\\) needs the env made with render_mode"):
            env.render()
        env.close()


@pytest.mark.parametrize("task_id,settings,hw", DOMAINS)
def test_close_twice_does_nothing_the_second_time(task_id, settings, hw):
    _need(task_id)
    env = rlu.make_env(task_id, seed=0, render_mode="rgb_array", **settings)
    env.reset(seed=0)
    env.render()
    env.close()
    env.close()
    wrapped = gym.make(rlu.get_task(task_id).gym_id, **settings)
    wrapped.close()
    wrapped.close()


def test_locomotion_close_twice_after_a_seeded_rebuild():
    _need("locomotion/rodent_gaps")
    env = rlu.make_env("locomotion/rodent_gaps", seed=0, camera=False)
    env.reset(seed=3)  # rebuilds the composer env and closes the first
    env.close()
    env.close()


# --- the real time limit in the spec -------------------------------------------------------------


def test_spec_max_episode_steps_is_each_dm_control_envs_step_limit():
    pytest.importorskip("dm_control")
    for task in rlu.list_tasks("control_suite") + rlu.list_tasks("rwrl"):
        env = rlu.make_env(task.id)
        # dm_control.rl.control.Environment ends an episode once step_count >= this limit
        limit = int(np.ceil(env.raw_env._step_limit))
        assert env.spec.max_episode_steps == limit == task.episode_length, task.id
        assert gym.spec(task.gym_id).max_episode_steps == limit
        env.close()


def test_a_gymnasium_made_episode_ends_where_the_env_ends_it():
    """gymnasium.make wraps a TimeLimit of the spec's max_episode_steps: it must truncate at the
    very step the env's own time limit does (1000 for the control suite), not before."""
    pytest.importorskip("dm_control")
    env = gym.make("rlu/control_suite-cartpole_swingup-v0")
    assert env.spec.max_episode_steps == 1000
    env.reset(seed=0)
    inner = env.unwrapped
    steps, own = 0, None
    while True:
        _, _, terminated, truncated, info = env.step(np.zeros(1, np.float32))
        steps += 1
        if terminated or truncated:
            break
    # the unwrapped env's own last step: dm_control says LAST with discount 1 (truncation)
    own = inner.raw_env._step_count
    assert (steps, own, truncated, terminated, info["discount"]) == (1000, 1000, True, False, 1.0)
    env.close()


def test_atari_spec_follows_the_max_episode_steps_setting():
    pytest.importorskip("ale_py")
    assert gym.spec("rlu/atari-Pong-v0").max_episode_steps == 27_000
    env = rlu.make_env("atari/Pong", seed=0, max_episode_steps=40)
    assert env.spec.max_episode_steps == 40
    again = gym.make(env.spec)  # the spec makes the same 40-step env, TimeLimit and all
    for e in (env, again):
        e.reset(seed=0)
        n = 0
        while True:
            _, _, terminated, truncated, _ = e.step(0)
            n += 1
            if terminated or truncated:
                break
        assert (n, truncated) == (40, True)
        e.close()


def _time_limit_steps(task_id: str) -> int:
    """Steps of one episode of the real env run to its time limit (termination switched off)."""
    env = rlu.make_env(task_id, seed=0, camera=False)
    env.raw_env.env.task.should_terminate_episode = lambda physics: False
    env.reset()
    n = 0
    while True:
        _, _, terminated, truncated, _ = env.step(np.zeros(env.action_space.shape, np.float32))
        n += 1
        if terminated or truncated:
            env.close()
            return n


# ~10 s each on one core: two in the quick suite (a humanoid and the 1000-step rodent task).
LOCOMOTION_SLOW = ["humanoid_walls", "humanoid_gaps", "rodent_gaps", "rodent_two_touch"]


@pytest.mark.parametrize(
    "name",
    ["humanoid_corridor", "rodent_bowl_escape"]
    + [pytest.param(n, marks=pytest.mark.slow) for n in [*LOCOMOTION_SLOW, "rodent_mazes"]],
)
def test_locomotion_episode_length_is_the_envs_own(name):
    """composer ends an episode once physics time >= the time limit: 1001 steps for the humanoid
    (its 6000 additions of 0.005 s fall short of 30 s), 1000 / 1500 for the rodents."""
    _need("locomotion/" + name)
    task = rlu.get_task("locomotion/" + name)
    n = _time_limit_steps(task.id)
    assert n == task.episode_length == gym.spec(task.gym_id).max_episode_steps
