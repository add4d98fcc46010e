"""The agent contract (d3rlpy-style) over every discrete agent, on fake Atari specs."""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import DISCRETE_AGENTS, agent_module, make_agent, make_config  # noqa: E402
from rlu.types import ArraySpec, SpecError  # noqa: E402
from tests.fakes import ATARI_ACTION, ATARI_OBS, CONT_ACTION, fake_transition  # noqa: E402

# Smaller than the small preset so the whole contract runs in seconds; shapes stay Atari's.
TINY = {"channels": (4, 8, 8), "hidden_size": 16}
TARGET = {"target_update_period": 1}  # so the target net moves inside the test too


def build(name: str, seed: int = 0, **overrides):
    module = agent_module(name, True)
    fields = {f.name for f in dataclasses.fields(module.Config)}
    extra = {k: v for k, v in TARGET.items() if k in fields}
    return make_agent(name, ATARI_OBS, ATARI_ACTION, "small", seed, **TINY, **extra, **overrides)


def batches(n: int, size: int = 6):
    return [fake_transition(ATARI_OBS, ATARI_ACTION, batch=size, seed=s) for s in range(n)]


def parameters(agent) -> list[torch.Tensor]:
    return [p.detach().clone() for p in agent.learner.network.parameters()]


@pytest.mark.parametrize("name", DISCRETE_AGENTS)
def test_module_convention(name):
    module = agent_module(name, True)
    assert set(module.PRESETS) >= {"paper", "small"}
    assert module.Agent.batch_kind == "transition"
    config = module.PRESETS["paper"]
    assert isinstance(config, module.Config)
    assert dataclasses.is_dataclass(config) and module.Config.__dataclass_params__.frozen
    fields = {f.name for f in dataclasses.fields(config)}
    assert set(module.GRID) <= fields
    assert module.GRID["learning_rate"] == [3e-5, 5e-5, 1e-4]
    # the paper's table (appendix A.2)
    assert (config.channels, config.kernel_sizes, config.strides) == (
        (32, 64, 64),
        (8, 4, 3),
        (4, 2, 1),
    )
    assert config.hidden_size == 512 and config.batch_size == 256 and config.adam_eps == 1e-7
    assert config.num_steps == 2_000_000 and config.eval_epsilon == pytest.approx(0.4**8)
    if "discount" in fields:
        assert config.discount == 0.99 and config.target_update_period == 2500


def test_paper_presets_name_the_paper_choices():
    assert make_config("dqn", True, "paper").double_q is True
    assert make_config("iqn", True, "paper").num_tau_samples == 16
    assert make_config("bcq", True, "paper").threshold == 0.5
    assert make_config("rem", True, "paper").num_heads == 4
    assert agent_module("bcq", True).GRID["threshold"] == [0.25, 0.5, 0.75, 1.0]
    assert agent_module("iqn", True).GRID["num_tau_samples"] == [8, 16, 32]
    lrs = {n: make_config(n, True, "paper").learning_rate for n in DISCRETE_AGENTS}
    assert lrs == {"bc": 3e-5, "dqn": 3e-5, "iqn": 1e-4, "bcq": 1e-4, "rem": 1e-4}


@pytest.mark.parametrize("name", DISCRETE_AGENTS)
def test_paper_network_takes_atari_frames(name):
    agent = make_agent(name, ATARI_OBS, ATARI_ACTION, "paper")
    obs = fake_transition(ATARI_OBS, ATARI_ACTION, batch=2).observation
    action = agent.act(obs)
    assert action.shape == (2,) and action.dtype == np.int64


@pytest.mark.parametrize("name", DISCRETE_AGENTS)
def test_update_gives_finite_prefixed_metrics_and_moves_every_parameter(name):
    agent = build(name)
    before = parameters(agent)
    for batch in batches(2):
        metrics = agent.update(batch)
    assert metrics and all("/" in k for k in metrics)
    assert all(isinstance(v, float) and np.isfinite(v) for v in metrics.values()), metrics
    after = parameters(agent)
    names = [n for n, _ in agent.learner.network.named_parameters()]
    unchanged = [n for n, a, b in zip(names, before, after, strict=True) if torch.equal(a, b)]
    assert not unchanged, f"{name}: parameters not updated: {unchanged}"
    if agent.learner.target_network is not None:  # target copied every step here
        for p, t in zip(
            agent.learner.network.parameters(),
            agent.learner.target_network.parameters(),
            strict=True,
        ):
            assert torch.equal(p, t)


@pytest.mark.parametrize("name", DISCRETE_AGENTS)
@pytest.mark.parametrize("greedy", [True, False])
def test_actions_inside_the_spec(name, greedy):
    agent = build(name)
    agent.update(batches(1)[0])
    obs = fake_transition(ATARI_OBS, ATARI_ACTION, batch=64, seed=7).observation
    action = agent.act(obs, greedy=greedy)
    assert action.shape == (64,) and action.dtype == np.int64
    assert action.min() >= 0 and action.max() < ATARI_ACTION.num_values


@pytest.mark.parametrize("name", DISCRETE_AGENTS)
def test_state_dict_round_trip_keeps_greedy_actions_and_resumes_identically(name):
    agent = build(name, seed=3)
    data = batches(3)
    agent.update(data[0])
    buffer = io.BytesIO()
    torch.save(agent.state_dict(), buffer)
    buffer.seek(0)
    state = torch.load(buffer, weights_only=True)

    other = build(name, seed=99)
    other.load_state_dict(state)
    obs = fake_transition(ATARI_OBS, ATARI_ACTION, batch=32, seed=11).observation
    np.testing.assert_array_equal(agent.act(obs), other.act(obs))
    # a resumed run continues identically: same metrics, same weights after more updates
    for batch in data[1:]:
        assert agent.update(batch) == other.update(batch)
    for a, b in zip(parameters(agent), parameters(other), strict=True):
        assert torch.equal(a, b)
    np.testing.assert_array_equal(agent.act(obs, greedy=False), other.act(obs, greedy=False))


@pytest.mark.parametrize("name", DISCRETE_AGENTS)
def test_same_seed_same_numbers_other_seed_other_numbers(name):
    data = batches(2)
    obs = fake_transition(ATARI_OBS, ATARI_ACTION, batch=16, seed=5).observation

    def run(seed):
        torch.manual_seed(1234 + seed)  # the global RNG must not matter
        agent = build(name, seed=seed)
        metrics = [agent.update(b) for b in data]
        return metrics, agent.act(obs), parameters(agent)

    m0, a0, p0 = run(0)
    m1, a1, p1 = run(0)
    m2, _, p2 = run(1)
    assert m0 == m1
    np.testing.assert_array_equal(a0, a1)
    assert all(torch.equal(a, b) for a, b in zip(p0, p1, strict=True))
    assert m0 != m2 and not all(torch.equal(a, b) for a, b in zip(p0, p2, strict=True))


@pytest.mark.parametrize("name", DISCRETE_AGENTS)
def test_bad_specs_and_batches_are_named(name):
    module = agent_module(name, True)
    config = module.PRESETS["small"]
    with pytest.raises(SpecError, match="DiscreteSpec"):
        module.Agent(ATARI_OBS, CONT_ACTION, config)
    with pytest.raises(SpecError, match="uint8"):
        module.Agent(ArraySpec((84, 84, 4), "float32"), ATARI_ACTION, config)
    with pytest.raises(SpecError, match="frame stack"):
        module.Agent(ArraySpec((7,), "uint8"), ATARI_ACTION, config)
    agent = build(name)
    batch = batches(1)[0]
    bad = batch._replace(observation=batch.observation.astype(np.float32))
    with pytest.raises(SpecError, match="batch.observation"):
        agent.update(bad)


def test_read_only_batches_are_accepted():
    agent = build("dqn")
    batch = batches(1)[0]
    for array in (batch.observation, batch.next_observation):
        array.setflags(write=False)
    assert np.isfinite(agent.update(batch)["critic/loss"])


def test_bc_and_bcq_names_pick_the_discrete_variant_from_the_action_spec():
    assert type(build("bc")).__module__ == "rlu.agents.bc_discrete"
    assert type(build("bcq")).__module__ == "rlu.agents.bcq_discrete"


@pytest.mark.parametrize("name", ["dqn", "iqn", "bcq", "rem"])
def test_n_step_agents_discount_by_gamma_to_the_n(name):
    # the views give the n-step reward sum and the product of discounts without gamma^n
    agent = build(name, n_step=3)
    assert agent.n_step == 3
    assert agent.learner.loss.discount == pytest.approx(0.99**3)


def test_greedy_means_what_the_docstrings_say():
    obs = fake_transition(ATARI_OBS, ATARI_ACTION, batch=64, seed=3).observation
    frames = torch.from_numpy(obs)
    with torch.no_grad():
        # BC: the max action of the policy head
        bc = build("bc", eval_epsilon=0.0)
        np.testing.assert_array_equal(bc.act(obs), bc.learner.network(frames).argmax(-1).numpy())
        # BCQ at threshold 1: only the imitation head's argmax is allowed
        bcq = build("bcq", eval_epsilon=0.0, threshold=1.0)
        _, logits = bcq.learner.network(frames)
        np.testing.assert_array_equal(bcq.act(obs), logits.argmax(-1).numpy())
        # REM: argmax of the mean of the heads
        rem = build("rem", eval_epsilon=0.0)
        expected = rem.learner.network(frames).mean(1).argmax(-1).numpy()
        np.testing.assert_array_equal(rem.act(obs), expected)
    # epsilon 1 acts uniformly at random
    dqn = build("dqn", eval_epsilon=1.0)
    counts = np.bincount(dqn.act(np.repeat(obs, 10, axis=0)), minlength=6)
    assert counts.min() > 50
