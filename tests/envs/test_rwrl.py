"""RWRL envs: each challenge does what its definition says (rlu/domains/rwrl/env.py, with
sources)."""

import numpy as np
import pytest

pytest.importorskip("dm_control")

import rlu  # noqa: E402
from rlu.domains.envkit import check_observation, observation_space  # noqa: E402
from rlu.domains.rwrl.env import CHALLENGES, PERTURBATIONS  # noqa: E402
from rlu.tasks import list_tasks, rwrl_observation_spec  # noqa: E402
from tests.envs.helpers import check_env_quietly, rollout, same  # noqa: E402

TASKS = [t.id for t in list_tasks("rwrl")]
CART = "rwrl/cartpole_swingup"


@pytest.mark.parametrize("challenge", ["none", "easy"])
@pytest.mark.parametrize("task_id", TASKS)
def test_contract_spec_and_determinism(task_id, challenge):
    task = rlu.get_task(task_id)
    spec = rwrl_observation_spec(task, challenge)
    env = rlu.make_env(task_id, seed=0, challenge=challenge)
    assert env.observation_space == observation_space(spec)
    check_env_quietly(env)
    a = rollout(env, seed=3, steps=100)
    b = rollout(rlu.make_env(task_id, seed=11, challenge=challenge), seed=3, steps=100)
    assert all(same(x, y) for x, y in zip(a, b, strict=True))
    check_observation(a[-1], spec, task_id)


def test_easy_numbers_are_the_realworldrl_suite_definitions():
    e = CHALLENGES["easy"]
    assert (e.action_delay, e.observation_delay, e.reward_delay) == (3, 3, 10)
    assert (e.action_noise_std, e.observation_noise_std) == (0.1, 0.1)
    assert (e.observation_drop_prob, e.observation_drop_steps) == (0.01, 1)
    assert (e.observation_stuck_prob, e.observation_stuck_steps) == (0.01, 1)
    assert (e.action_repeat_prob, e.action_repeat_steps, e.num_dummy) == (1.0, 1, 10)
    assert (e.perturb, e.perturb_period, e.perturb_scheduler) == ("easy", 1, "uniform")
    assert PERTURBATIONS["walker"].levels["easy"] == (0.225, 0.25, 0.002)
    assert PERTURBATIONS["humanoid"].levels["easy"][:2] == (0.6, 0.8)


def _controls(env, actions):
    env.reset(seed=0)
    out = []
    for a in actions:
        env.step(a)
        out.append(env.raw_env.physics.control().copy())
    return np.array(out)


def test_action_delay_shifts_actions_by_k_steps():
    actions = [np.array([v], np.float32) for v in np.linspace(-0.9, 0.9, 12)]
    got = _controls(rlu.make_env(CART, challenge="none", action_delay=3), actions)
    want = np.array([actions[max(t - 3, 0)] for t in range(12)])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-7)


def test_action_repetition_holds_each_fresh_action_for_k_steps():
    actions = [np.array([v], np.float32) for v in np.linspace(-0.9, 0.9, 9)]
    env = rlu.make_env(CART, challenge="none", action_repeat_prob=1.0, action_repeat_steps=3)
    got = _controls(env, actions)
    want = np.array([actions[3 * (t // 3)] for t in range(9)])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-7)


def test_action_noise_has_the_specified_std():
    zeros = [np.zeros(1, np.float32)] * 2000
    got = _controls(rlu.make_env(CART, seed=0, action_noise_std=0.1), zeros)
    assert abs(got.std() - 0.1) < 0.01 and abs(got.mean()) < 0.01


def _paired(steps=200, **challenge):
    """Observations and rewards of a clean and a challenged env under the same seed/actions."""
    clean = rlu.make_env(CART, seed=4)
    noisy = rlu.make_env(CART, seed=4, **challenge)
    oc, _ = clean.reset()
    on, _ = noisy.reset()
    obs, rew = [(oc, on)], []
    rng = np.random.default_rng(0)
    for _ in range(steps):
        a = rng.uniform(-1, 1, 1).astype(np.float32)
        oc, rc, *_ = clean.step(a)
        on, rn, *_ = noisy.step(a)
        obs.append((oc, on))
        rew.append((rc, rn))
    return obs, np.array(rew)


def test_observation_noise_has_the_specified_std():
    obs, _ = _paired(observation_noise_std=0.1)
    diff = np.concatenate([n[k] - c[k] for c, n in obs for k in c])
    assert abs(diff.std() - 0.1) < 0.01 and abs(diff.mean()) < 0.01


def test_observation_and_reward_delays_shift_by_k_steps():
    obs, rew = _paired(observation_delay=2, reward_delay=10)
    for t in range(len(obs)):
        c, n = obs[max(t - 2, 0)][0], obs[t][1]
        assert same(c, n)
    np.testing.assert_array_equal(rew[10:, 1], rew[:-10, 0])
    np.testing.assert_array_equal(rew[:10, 1], np.full(10, rew[0, 0]))


def test_dropped_observations_are_zero_and_stuck_ones_repeat():
    obs, _ = _paired(observation_drop_prob=0.3, observation_drop_steps=1)
    dropped = np.concatenate([(n[k] == 0) & (c[k] != 0) for c, n in obs for k in c])
    kept = np.concatenate([n[k] == c[k] for c, n in obs for k in c])
    assert abs(dropped.mean() - 0.3) < 0.05 and np.all(dropped | kept)
    obs, _ = _paired(observation_stuck_prob=0.3, observation_stuck_steps=2)
    # A stuck element repeats the previous output; the clean env moves on.
    stuck = np.concatenate(
        [(obs[t][1][k] == obs[t - 1][1][k]) & (obs[t][0][k] != obs[t - 1][0][k])
         for t in range(2, len(obs)) for k in obs[t][0]]
    )  # fmt: skip
    assert 0.3 < stuck.mean() < 0.7


def test_easy_dummies_are_standard_normal_and_not_delayed():
    env = rlu.make_env(CART, seed=0, challenge="easy")
    env.reset()
    steps = [env.step(np.zeros(1, np.float32))[0] for _ in range(300)]
    d = np.array([[o[f"dummy-{i}"][0] for i in range(10)] for o in steps])
    assert abs(d.std() - 1.0) < 0.05 and abs(d.mean()) < 0.05


@pytest.mark.parametrize(
    "task_id,measure,lo,hi,nominal",
    [
        (CART, lambda m: 2 * m.geom_size[m.name2id("pole_1", "geom"), 1], 0.9, 1.1, 1.0),
        ("rwrl/walker_walk", lambda m: m.geom_size[m.name2id("right_thigh", "geom"), 1],
         0.225, 0.25, 0.225),
        ("rwrl/quadruped_walk", lambda m: 2 * m.geom_size[m.name2id("shin_front_left", "geom"), 1]
         / np.sqrt(2), 0.25, 0.3, 0.25),
        # The suite's floor keeps MuJoCo's default sliding friction 1.
        ("rwrl/humanoid_walk", lambda m: m.geom_friction[m.name2id("floor", "geom"), 0], 0.6, 0.8,
         1.0),
    ],
)  # fmt: skip
def test_easy_perturbation_resamples_the_parameter_each_episode(task_id, measure, lo, hi, nominal):
    env = rlu.make_env(task_id, seed=0, challenge="easy")
    values = []
    for _ in range(3):
        env.reset()
        values.append(float(measure(env.raw_env.physics.model)))
    assert all(lo - 1e-6 <= v <= hi + 1e-6 for v in values), values
    assert len(set(np.round(values, 6))) == 3
    plain = rlu.make_env(task_id, seed=0, challenge="none")
    plain.reset()
    assert float(measure(plain.raw_env.physics.model)) == pytest.approx(nominal)


CONSTRAINTS = [
    (CART, 3),
    ("rwrl/walker_walk", 4),
    ("rwrl/quadruped_walk", 4),
    ("rwrl/humanoid_walk", 5),
]


@pytest.mark.parametrize("task_id,n", CONSTRAINTS)
def test_constraints_appear_in_the_observations(task_id, n):
    env = rlu.make_env(task_id, seed=0, safety=True, multiobj_observed=True)
    check_env_quietly(env)
    obs, _ = env.reset()
    assert obs["constraints"].shape == (n,) and obs["constraints"].dtype == np.bool_
    for _ in range(20):
        obs, *_ = env.step(env.action_space.sample())
    assert set(np.unique(obs["constraints"])) <= {0, 1}
    assert obs["multiobj"].shape == (2,)
    assert obs["multiobj"][1] == pytest.approx(obs["constraints"].mean())


def test_strict_safety_is_violated_and_multiobj_reward_is_the_safety_score():
    env = rlu.make_env(CART, seed=0, safety=True, safety_coeff=0.0, multiobj_reward=True,
                       multiobj_coeff=1.0)  # fmt: skip
    env.reset()
    obs, r, *_ = env.step(np.ones(1, np.float32))
    assert r == pytest.approx(obs["constraints"].mean())
    assert obs["constraints"][0] == 0  # slider inside (-0, 0) is impossible


def test_quadruped_starts_upright_with_a_random_yaw():
    # rwrl/quadruped.py draws only a yaw; the suite task draws any 3-D orientation.
    ups = [rlu.make_env("rwrl/quadruped_walk", seed=s).reset()[0]["torso_upright"][0]
           for s in range(3)]  # fmt: skip
    np.testing.assert_allclose(ups, 1.0, atol=1e-6)


def test_delay_buffers_carry_over_episodes_but_a_seeded_reset_restarts_them():
    env = rlu.make_env(CART, seed=0, observation_delay=3)
    first, _ = env.reset()
    for _ in range(5):
        last, *_ = env.step(np.zeros(1, np.float32))
    carried, _ = env.reset()  # the observation of 3 steps before the end of episode 1
    assert any(not np.array_equal(carried[k], first[k]) for k in first)
    fresh, _ = env.reset(seed=0)
    assert same(fresh, first)


def test_bad_settings_are_clear():
    with pytest.raises(rlu.types.RluError, match="unknown RWRL challenge"):
        rlu.make_env(CART, challenge="extreme")
    with pytest.raises(rlu.types.RluError, match="safety_coeff"):
        rlu.make_env(CART, safety=True, safety_coeff=2.0)
    with pytest.raises(rlu.types.RluError, match="need safety"):
        rlu.make_env(CART, multiobj_observed=True)
