"""TD3+BC's target, critic and actor losses on hand-computed inputs; its delayed actor and
targets; and its observation statistics: set, used by ``act`` and ``update``, saved, restored,
and handed over by the training loop."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import make_agent, td3bc  # noqa: E402
from rlu.agents import networks as nets  # noqa: E402
from rlu.agents.losses import smoothed_target_action  # noqa: E402
from rlu.types import ArraySpec, DataStatistics, RluError  # noqa: E402
from tests.fakes import CONT_ACTION, IMAGE_OBS, LOWDIM_OBS, fake_transition  # noqa: E402

TINY = dict(hidden_layers=(16,), torso_hidden=8)


def t(x):
    return torch.tensor(x, dtype=torch.float32)


def close(a, b, tol=1e-6):
    a, b = (x.detach() if isinstance(x, torch.Tensor) else x for x in (a, b))
    np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), atol=tol)


def stats(spec, shift: float = 0.0, scale: float = 1.0) -> DataStatistics:
    rng = np.random.default_rng(0)
    mean = {k: rng.normal(size=s.shape) + shift for k, s in spec.items() if s.dtype != "uint8"}
    std = {k: rng.uniform(0.5, 2.0, s.shape) * scale for k, s in spec.items() if s.dtype != "uint8"}
    return DataStatistics(observation_mean=mean, observation_std=std)


def agent(seed=0, spec=LOWDIM_OBS, statistics=None, **kw):
    a = make_agent("td3bc", spec, CONT_ACTION, seed=seed, **{**TINY, **kw})
    if a.batch_spec.statistics:
        a.set_statistics(statistics or stats(spec))
    return a


def test_target_policy_smoothing_clips_the_noise_then_the_action():
    next_action = t([[0.9, -0.2], [0.0, -0.95]])
    eps = torch.randn((2, 2), generator=torch.Generator().manual_seed(3))
    got = smoothed_target_action(next_action, 0.2, 0.5, torch.Generator().manual_seed(3))
    want = np.clip(next_action.numpy() + np.clip(0.2 * eps.numpy(), -0.5, 0.5), -1.0, 1.0)
    close(got, want)
    # a huge sigma: every noise entry is clipped to +-0.5 (0.9 + 0.5 then clipped to 1)
    got = smoothed_target_action(next_action, 1e6, 0.5, torch.Generator().manual_seed(3))
    signs = np.sign(eps.numpy())
    close(got, np.clip(next_action.numpy() + 0.5 * signs, -1.0, 1.0))


def test_critic_target_bootstraps_the_smaller_target_critic():
    target = td3bc.critic_target(t([1.0, 0.5]), t([1.0, 0.0]), 0.99, t([[2.0, 3.0], [1.0, 5.0]]))
    close(target, [1.0 + 0.99 * 1.0, 0.5])  # min(2, 1) = 1; the terminal row keeps r only


def test_critic_loss_sums_the_twin_mean_squared_errors_with_the_target_fixed():
    target = t([1.0, 1.0]).requires_grad_()
    loss, metrics = td3bc.critic_loss(t([[1.0, 2.0], [3.0, 4.0]]).requires_grad_(), target)
    close(loss, (0.0 + 1.0) / 2 + (4.0 + 9.0) / 2)  # 7
    close(metrics["critic/q_mean"], 2.5)
    loss.backward()
    assert target.grad is None


def test_actor_loss_weighs_q_by_alpha_over_its_mean_magnitude_held_fixed():
    q = t([2.0, -4.0]).requires_grad_()
    pi = t([[0.5], [0.0]]).requires_grad_()
    loss, metrics = td3bc.actor_loss(q, pi, t([[0.0], [1.0]]), 2.5)
    lmbda = 2.5 / 3.0  # alpha / mean |Q| = 2.5 / ((2 + 4) / 2)
    close(metrics["actor/lambda"], lmbda)
    close(metrics["actor/bc_loss"], (0.25 + 1.0) / 2)
    close(loss, -lmbda * -1.0 + 0.625)  # 1.4583...
    loss.backward()
    close(q.grad, [-lmbda / 2, -lmbda / 2])  # no gradient through lambda's |Q|
    close(pi.grad, [[2 * 0.5 / 2], [2 * -1.0 / 2]])  # d/dpi mean (pi - a)^2


def test_twin_critic_first_is_the_first_critic_alone():
    critics = nets.TwinCritic(LOWDIM_OBS, 3, (8,), 4)
    batch = fake_transition(LOWDIM_OBS, CONT_ACTION, 5)
    obs = {k: torch.from_numpy(v) for k, v in batch.observation.items()}
    a = torch.from_numpy(batch.action)
    close(critics.first(obs, a), critics(obs, a)[0])


def _params(module):
    return [p.detach().clone() for p in module.parameters()]


def _equal(a, b):
    return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


def test_actor_and_targets_learn_on_every_second_update_only():
    ag = agent(tau=0.1)
    data = [fake_transition(LOWDIM_OBS, CONT_ACTION, 6, i) for i in range(2)]
    actor0, critic0 = _params(ag.actor), _params(ag.critics)
    m1 = ag.update(data[0])
    assert not any(k.startswith("actor/") for k in m1)
    assert _equal(_params(ag.actor), actor0) and not _equal(_params(ag.critics), critic0)
    assert _equal(_params(ag.target_actor), actor0) and _equal(_params(ag.target_critics), critic0)
    m2 = ag.update(data[1])  # update 2: critic, actor, then both targets move by tau = 0.1
    assert {"actor/loss", "actor/bc_loss", "actor/lambda", "actor/q_mean"} <= set(m2)
    assert not _equal(_params(ag.actor), actor0)
    for target, online, before in (
        (ag.target_actor, ag.actor, actor0), (ag.target_critics, ag.critics, critic0),
    ):  # fmt: skip
        for got, now, old in zip(_params(target), _params(online), before, strict=True):
            close(got, old + 0.1 * (now - old), 1e-7)  # towards the updated networks


def test_the_normaliser_standardises_float_entries_and_leaves_cameras_alone():
    norm = nets.ObservationNormaliser(IMAGE_OBS, 1e-3)
    assert norm.statistics == ("observation",) and not norm.ready
    mean = {"walker/joints_pos": np.arange(8.0)}
    std = {"walker/joints_pos": np.r_[np.zeros(4), np.full(4, 0.5)]}
    norm.set(DataStatistics(observation_mean=mean, observation_std=std))
    assert norm.ready
    x = np.linspace(-1, 1, 16, dtype=np.float32).reshape(2, 8)
    cam = torch.zeros((2, 64, 64, 3), dtype=torch.uint8)
    out = norm({"walker/joints_pos": torch.from_numpy(x), "walker/egocentric_camera": cam})
    close(out["walker/joints_pos"], (x - np.arange(8.0)) / (std["walker/joints_pos"] + 1e-3), 1e-3)
    assert out["walker/egocentric_camera"] is cam
    flat = nets.ObservationNormaliser(ArraySpec((2,), "float32"), 1e-3)
    flat.set(DataStatistics(observation_mean=np.array([1.0, 2.0]), observation_std=np.ones(2)))
    close(flat(t([[2.0, 2.0]])), [[1.0 / 1.001, 0.0]])
    off = nets.ObservationNormaliser(LOWDIM_OBS, 1e-3, enabled=False)
    assert off.statistics == () and off.ready
    obs = {"height": t([[3.0]])}
    assert off(obs) is obs


def test_statistics_that_do_not_fit_are_refused_naming_the_entry():
    norm = nets.ObservationNormaliser(LOWDIM_OBS, 1e-3)
    good = stats(LOWDIM_OBS)
    missing = DataStatistics(
        observation_mean={k: v for k, v in good.observation_mean.items() if k != "height"},
        observation_std=good.observation_std,
    )
    with pytest.raises(RluError, match="no observation mean of 'height'"):
        norm.set(missing)
    wrong = dict(good.observation_mean, velocity=np.zeros(4))
    with pytest.raises(RluError, match="'velocity' has shape \\(4,\\)"):
        norm.set(DataStatistics(observation_mean=wrong, observation_std=good.observation_std))
    with pytest.raises(RluError, match="not finite"):
        bad = dict(good.observation_std, height=np.array([np.nan]))
        norm.set(DataStatistics(observation_mean=good.observation_mean, observation_std=bad))


def test_an_update_before_the_statistics_is_refused_and_without_normalisation_needs_none():
    ag = make_agent("td3bc", LOWDIM_OBS, CONT_ACTION, **TINY)
    assert ag.batch_spec.statistics == ("observation",)
    with pytest.raises(RluError, match="set_statistics"):
        ag.update(fake_transition(LOWDIM_OBS, CONT_ACTION, 6))
    off = make_agent("td3bc", LOWDIM_OBS, CONT_ACTION, normalize_observations=False, **TINY)
    assert off.batch_spec.statistics == ()
    assert np.isfinite(off.update(fake_transition(LOWDIM_OBS, CONT_ACTION, 6))["critic/loss"])


def _shifted(obs, by):
    return {k: v + np.float32(by) for k, v in obs.items()}


def test_shifting_the_data_and_its_statistics_together_changes_nothing():
    """The statistics are used by act and update: observations shifted by 3 with a mean
    shifted by 3 give the same actions and the same learning (to float rounding), and the
    unshifted observations other actions."""
    a = agent(0, statistics=stats(LOWDIM_OBS))
    b = agent(0, statistics=stats(LOWDIM_OBS, shift=3.0))
    obs = fake_transition(LOWDIM_OBS, CONT_ACTION, 4, seed=9).observation
    close(a.act(obs), b.act(_shifted(obs, 3.0)), 1e-5)
    assert not np.allclose(a.act(obs), b.act(obs), atol=1e-3)
    for i in range(4):
        batch = fake_transition(LOWDIM_OBS, CONT_ACTION, 6, seed=i)
        moved = batch._replace(
            observation=_shifted(batch.observation, 3.0),
            next_observation=_shifted(batch.next_observation, 3.0),
        )
        ma, mb = a.update(batch), b.update(moved)
        assert ma.keys() == mb.keys()
        close(list(ma.values()), list(mb.values()), 1e-4)
    close(a.act(obs), b.act(_shifted(obs, 3.0)), 1e-4)


def test_the_statistics_travel_in_the_state():
    b = agent(0, statistics=stats(LOWDIM_OBS, shift=3.0, scale=2.0))
    b.update(fake_transition(LOWDIM_OBS, CONT_ACTION, 6))
    fresh = make_agent("td3bc", LOWDIM_OBS, CONT_ACTION, seed=5, **TINY)  # none set
    fresh.load_state_dict(b.state_dict())
    obs = fake_transition(LOWDIM_OBS, CONT_ACTION, 4, seed=9).observation
    np.testing.assert_array_equal(fresh.act(obs), b.act(obs))
    batch = fake_transition(LOWDIM_OBS, CONT_ACTION, 6, seed=1)
    assert fresh.update(batch) == b.update(batch)  # a loaded state is ready to learn


def test_the_training_loop_hands_over_the_dataset_statistics_and_checkpoints_keep_them(tmp_path):
    from rlu.data import open_dataset
    from rlu.data.statistics import dataset_statistics
    from rlu.data.store import Schema
    from rlu.data.synthetic import write_synthetic
    from rlu.tasks import get_task
    from rlu.training.restore import load_agent
    from rlu.training.train import train
    from tests.fakes import train_config

    task = "control_suite/cartpole_swingup"
    path = write_synthetic(tmp_path / "data", Schema.for_task(get_task(task)), 3, 40)
    want = dataset_statistics(open_dataset(path), ("observation",))
    cfg = train_config(
        task=task, agent="td3bc", dataset=str(path), steps=2, eval_every=-1, log_every=1,
        checkpoint_every=2, torch_threads=1, overrides={"batch_size": 8, **TINY},
    )  # fmt: skip
    train(cfg, tmp_path / "run")
    restored, _ = load_agent(tmp_path / "run")
    norm = restored.normaliser
    assert norm.ready and norm.keys == sorted(want.observation_mean)
    for i, key in enumerate(norm.keys):
        close(norm.get_buffer(f"mean_{i}"), want.observation_mean[key])
        close(norm.get_buffer(f"std_{i}"), want.observation_std[key])
