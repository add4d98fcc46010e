"""The one contract every registered agent meets (d3rlpy's contract test), through its public
API only: it runs over ``rlu.agents.AGENTS``, so a new agent is tested by being registered.

Cases: continuous agents on low-dimensional dict observations, on features + a camera image and,
where the config has ``recurrent``, on sequence windows; discrete agents on Atari frame stacks
(windows of them where the config has ``recurrent``).
``SHRINK`` makes the networks tiny so the file runs in seconds (the code paths are the presets'
own); an agent without an entry runs its ``small`` preset.
"""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import AGENTS, agent_module, make_agent  # noqa: E402
from rlu.types import ArraySpec, BatchSpec, BoundedSpec, DataStatistics, SpecError  # noqa: E402
from tests.fakes import (  # noqa: E402
    ATARI_ACTION,
    ATARI_OBS,
    IMAGE_OBS,
    LOWDIM_OBS,
    fake_sequence,
    fake_transition,
)

# An off-centre box, so the [-1, 1] <-> spec mapping is exercised too.
BOX = BoundedSpec((3,), "float32", -2.0, 0.5)
TINY_ATARI = {"atari.channels": (4, 8, 8), "atari.hidden_size": 16}

# Tiny networks; phases short enough that three updates reach every trainable parameter.
SHRINK = {
    ("bc", False): dict(hidden_size=32, num_layers=2, lstm_hidden=16, sequence_length=5),
    ("d4pg", False): dict(policy_layers=(32, 32), critic_layers=(32, 32), torso_hidden=16),
    ("bcq", False): dict(actor_layers=(32,), critic_layers=(32,), vae_layers=(32,),
                         torso_hidden=16),
    ("brac", False): dict(policy_layers=(32,), critic_layers=(32,), behaviour_layers=(32,),
                          torso_hidden=16, behaviour_steps=1, warm_start_steps=1),
    ("rabm", False): dict(hidden_size=32, num_layers=2, lstm_hidden=16, sequence_length=5,
                          num_samples=4),
    ("crr", False): dict(hidden_size=32, num_layers=2, torso_hidden=16, num_advantage_samples=2),
    ("iql", False): dict(hidden_layers=(32,), torso_hidden=16),
    ("cql", False): dict(policy_layers=(32,), critic_layers=(32,), torso_hidden=16, bc_steps=1,
                         num_samples=2),
    ("td3bc", False): dict(hidden_layers=(32,), torso_hidden=16),
    # with the observation normalisation the original leaves off, so the contract covers it
    ("rebrac", False): dict(actor_layers=(32,), critic_layers=(32,), torso_hidden=16,
                            normalize_observations=True),
    ("dt", False): dict(context_length=4, num_layers=1, hidden_size=16, num_heads=2,
                        torso_hidden=16, warmup_steps=1),
    ("dt", True): {"atari.context_length": 3, "atari.num_layers": 1, "atari.num_heads": 2,
                   "atari.batch_size": 4, "atari.max_timestep": 50},
    ("bc", True): {"lstm_size": 8, "sequence_length": 4},
    ("r2d2", True): {"atari.batch_size": 4, "atari.n_step": 2, "lstm_size": 8,
                     "sequence_length": 3, "burn_in": 2},
}  # fmt: skip
# Agents that learn from sequence windows whatever the observations (no `recurrent` switch).
ALWAYS_SEQUENCE = {"dt", "r2d2"}
UPDATES = 3


def cases() -> list[tuple[str, bool, str]]:
    out = []
    for name, discrete in sorted(AGENTS):
        if discrete:
            out.append((name, True, "atari"))
            fields = {f.name for f in dataclasses.fields(agent_module(name, True).Config)}
            if "recurrent" in fields:
                out.append((name, True, "atari_sequence"))
            continue
        out += [(name, False, "lowdim"), (name, False, "image")]
        fields = {f.name for f in dataclasses.fields(agent_module(name, False).Config)}
        if "recurrent" in fields:
            out.append((name, False, "sequence"))
    return out


CASES = cases()
IDS = [f"{n}-{'discrete' if d else 'continuous'}-{k}" for n, d, k in CASES]


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    # Tiny tensors: intra-op threads only add synchronisation (many times slower on a busy CPU).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def specs(kind: str):
    if kind in ("atari", "atari_sequence"):
        return ATARI_OBS, ATARI_ACTION
    return (IMAGE_OBS if kind == "image" else LOWDIM_OBS), BOX


def build(name: str, discrete: bool, kind: str, seed: int = 0, **extra):
    obs_spec, action_spec = specs(kind)
    overrides = dict(TINY_ATARI if discrete else {}, **SHRINK.get((name, discrete), {}))
    if kind in ("sequence", "atari_sequence"):
        overrides["recurrent"] = True
    agent = make_agent(name, obs_spec, action_spec, seed=seed, **overrides, **extra)
    if agent.batch_spec.statistics:  # what the loop does before the first update
        agent.set_statistics(fake_statistics(obs_spec, seed))
    return agent


def fake_statistics(obs_spec, seed: int) -> DataStatistics:
    """Dataset statistics that differ by seed, so a state round trip (into an agent built with
    another seed) must carry them for the actions to match."""
    rng = np.random.default_rng(1000 + seed)
    specs = {"": obs_spec} if isinstance(obs_spec, ArraySpec) else obs_spec
    floats = {k: s.shape for k, s in specs.items() if np.dtype(s.dtype) != np.uint8}
    mean = {k: rng.normal(size=shape).astype(np.float32) for k, shape in floats.items()}
    std = {k: rng.uniform(0.5, 2.0, shape).astype(np.float32) for k, shape in floats.items()}
    if isinstance(obs_spec, ArraySpec):
        mean, std = mean.get(""), std.get("")
    return DataStatistics(mean, std, 0.5, 0.25, 0.0, 1.0, 0.0, 1000.0)


def batches(agent, kind: str, n: int = UPDATES, seed: int = 0):
    obs_spec, action_spec = specs(kind)
    spec = agent.batch_spec
    if spec.kind == "sequence":
        length = spec.sequence_length
        return [fake_sequence(obs_spec, action_spec, 4, length, seed + i) for i in range(n)]
    return [fake_transition(obs_spec, action_spec, 6, seed + i) for i in range(n)]


def observation(kind: str, n: int = 5, seed: int = 99):
    obs_spec, action_spec = specs(kind)
    return fake_transition(obs_spec, action_spec, batch=n, seed=seed).observation


def trainable(agent) -> dict[str, torch.Tensor]:
    return {
        f"{m}.{k}": p.detach().clone()
        for m, module in agent.modules.items()
        for k, p in module.named_parameters()
        if p.requires_grad
    }


def everything(agent) -> dict[str, torch.Tensor]:
    return {
        f"{m}.{k}": p.detach().clone()
        for m, module in agent.modules.items()
        for k, p in module.state_dict().items()
    }


@pytest.mark.parametrize(("name", "discrete"), sorted(AGENTS), ids=lambda x: str(x))
def test_module_convention(name, discrete):
    module = agent_module(name, discrete)
    assert set(module.PRESETS) >= {"paper", "small"}
    assert dataclasses.is_dataclass(module.Config) and module.Config.__dataclass_params__.frozen
    assert module.PRESETS["paper"] == module.Config()  # the paper preset is the defaults
    for preset in module.PRESETS.values():
        assert isinstance(preset, module.Config)
    fields = {f.name for f in dataclasses.fields(module.Config)}
    assert set(module.GRID) <= fields and all(module.GRID.values())
    for f in dataclasses.fields(module.Config):  # every field says what it is
        assert f.type, f"{name}: field {f.name} has no annotation"
    assert module.__doc__ and len(module.__doc__) > 200, f"{name}: module docstring (paper, code)"


@pytest.mark.parametrize(("name", "discrete", "kind"), CASES, ids=IDS)
def test_update_gives_metrics_and_moves_every_trainable_parameter(name, discrete, kind):
    agent = build(name, discrete, kind)
    assert isinstance(agent.batch_spec, BatchSpec)
    assert isinstance(agent.pretrain_steps, int) and agent.pretrain_steps >= 0
    assert isinstance(agent.num_steps, int) and agent.num_steps >= 1
    sequence = kind in ("sequence", "atari_sequence") or name in ALWAYS_SEQUENCE
    assert agent.batch_spec.kind == ("sequence" if sequence else "transition")
    before = trainable(agent)
    assert before, f"{name}: agent.modules holds no trainable parameter"
    for batch in batches(agent, kind):
        metrics = agent.update(batch)
    assert metrics and all(isinstance(v, float) and np.isfinite(v) for v in metrics.values())
    assert all("/" in k for k in metrics), f"metric keys carry a prefix: {list(metrics)}"
    after = trainable(agent)
    frozen = [k for k in before if torch.equal(before[k], after[k])]
    assert not frozen, f"{name}: parameters never changed: {frozen}"


@pytest.mark.parametrize(("name", "discrete", "kind"), CASES, ids=IDS)
def test_actions_lie_inside_the_action_spec(name, discrete, kind):
    agent = build(name, discrete, kind)
    for batch in batches(agent, kind):
        agent.update(batch)
    _, action_spec = specs(kind)
    obs = observation(kind, 6)
    first = np.ones(6, bool)
    for greedy in (True, False):
        a = agent.act(obs, greedy=greedy, is_first=first)
        assert a.shape == (6, *action_spec.shape) and a.dtype == np.dtype(action_spec.dtype)
        if discrete:
            assert a.min() >= 0 and a.max() < action_spec.num_values
        else:
            assert np.all(np.isfinite(a))
            assert np.all(a >= action_spec.minimum) and np.all(a <= action_spec.maximum)


@pytest.mark.parametrize(("name", "discrete", "kind"), CASES, ids=IDS)
def test_act_takes_the_reward_of_each_rows_previous_action(name, discrete, kind):
    """Evaluation hands every policy what each row's previous action earned (``reward``, 0
    where ``is_first``; ``rlu.types.Policy``): every agent takes it, and rows that go on act
    with it (a return-conditioned agent lowers its return to go; the others ignore it)."""
    agent = build(name, discrete, kind)
    agent.update(batches(agent, kind, 1)[0])
    _, action_spec = specs(kind)
    obs = observation(kind, 4)
    first = agent.act(obs, greedy=True, is_first=np.ones(4, bool), reward=np.zeros(4))
    later = agent.act(
        obs, greedy=True, is_first=np.array([0, 1, 0, 0], bool), reward=np.array([1, 0, -2, 0.5])
    )
    assert first.shape == later.shape == (4, *action_spec.shape)
    assert later.dtype == np.dtype(action_spec.dtype)


@pytest.mark.parametrize(("name", "discrete", "kind"), CASES, ids=IDS)
def test_state_round_trip_resumes_identically(name, discrete, kind):
    agent = build(name, discrete, kind, seed=0)
    data = batches(agent, kind)
    agent.update(data[0])
    buffer = io.BytesIO()
    torch.save(agent.state_dict(), buffer)
    buffer.seek(0)
    state = torch.load(buffer, weights_only=True)  # plain tensors and containers only

    other = build(name, discrete, kind, seed=123)
    other.load_state_dict(state)
    obs, first = observation(kind), np.ones(5, bool)
    np.testing.assert_array_equal(agent.act(obs, is_first=first), other.act(obs, is_first=first))
    # Networks, optimisers, step counters and RNG state all travel: the next updates match.
    for batch in data[1:]:
        assert agent.update(batch) == other.update(batch)
    a, b = everything(agent), everything(other)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    np.testing.assert_array_equal(
        agent.act(obs, greedy=False, is_first=first), other.act(obs, greedy=False, is_first=first)
    )


def _flat(state, prefix=""):
    """Every tensor of a nested state, by its path."""
    if isinstance(state, torch.Tensor):
        return {prefix: state}
    if isinstance(state, dict):
        items = state.items()
    elif isinstance(state, (list, tuple)):
        items = enumerate(state)
    else:
        return {}
    return {k: v for key, sub in items for k, v in _flat(sub, f"{prefix}/{key}").items()}


@pytest.mark.parametrize(("name", "discrete", "kind"), CASES, ids=IDS)
def test_state_dict_is_a_snapshot_and_loaded_copies_share_nothing(name, discrete, kind):
    """In memory, without a file between: the state taken before an update stays as it was, and
    two agents loaded from it train exactly as the source did from there (each on its own
    optimiser moments)."""
    agent = build(name, discrete, kind, seed=0)
    data = batches(agent, kind)
    agent.update(data[0])  # Adam has moments now
    state = agent.state_dict()
    frozen = {k: v.clone() for k, v in _flat(state).items()}
    copies = [build(name, discrete, kind, seed=s) for s in (1, 2)]
    for other in copies:
        other.load_state_dict(state)
    expected = agent.update(data[1])
    flat = _flat(state)
    assert flat.keys() == frozen.keys()
    assert all(torch.equal(flat[k], frozen[k]) for k in flat), "the update moved the state"
    for other in copies:
        assert other.update(data[1]) == expected
    a, b, c = everything(agent), *(everything(o) for o in copies)
    assert all(torch.equal(a[k], b[k]) and torch.equal(a[k], c[k]) for k in a)


@pytest.mark.parametrize(("name", "discrete", "kind"), CASES, ids=IDS)
def test_same_seed_same_numbers_other_seed_other_numbers_global_rng_untouched(name, discrete, kind):
    results = []
    for seed in (7, 7, 8):
        torch.manual_seed(1234 + seed)  # the global RNG must not matter ...
        expected = torch.get_rng_state()
        agent = build(name, discrete, kind, seed=seed)
        metrics = [agent.update(b) for b in batches(agent, kind)]
        actions = agent.act(observation(kind), greedy=False, is_first=np.ones(5, bool))
        assert torch.equal(torch.get_rng_state(), expected)  # ... nor be touched
        results.append((metrics, actions, everything(agent)))
    (m0, a0, p0), (m1, a1, p1), (m2, _, p2) = results
    assert m0 == m1
    np.testing.assert_array_equal(a0, a1)
    assert all(torch.equal(p0[k], p1[k]) for k in p0)
    assert m0 != m2 and not all(torch.equal(p0[k], p2[k]) for k in p0)


@pytest.mark.parametrize(("name", "discrete"), sorted(AGENTS), ids=lambda x: str(x))
def test_each_generator_is_its_own_stream_of_the_seed(name, discrete):
    """Learner noise, acting and dropout draw from ``rlu.seeds.stream_seed`` streams of the
    seed, one per generator; none is seeded with the seed that built the weights."""
    from rlu.seeds import STREAMS, stream_seed

    seed = 5
    agent = build(name, discrete, "atari" if discrete else "lowdim", seed=seed)
    streams = {stream_seed(seed, s) for s in STREAMS}
    seeds = {key: g.initial_seed() for key, g in agent.generators.items()}
    assert set(seeds.values()) <= streams, seeds
    assert len({id(g) for g in agent.generators.values()}) == len(set(seeds.values())), seeds


@pytest.mark.parametrize(("name", "discrete"), sorted(AGENTS), ids=lambda x: str(x))
def test_specs_of_the_other_action_type_are_refused(name, discrete):
    module = agent_module(name, discrete)
    config = module.PRESETS["small"]
    if AGENTS.get((name, not discrete)) == AGENTS[(name, discrete)]:
        # one module for both action types (dt): each kind of action refuses the other kind's
        # observations instead
        with pytest.raises(SpecError, match="uint8"):
            module.Agent(ArraySpec((84, 84, 4), "float32"), ATARI_ACTION, config)
        with pytest.raises(SpecError):
            module.Agent(LOWDIM_OBS, ATARI_ACTION, config)
        return
    if discrete:
        with pytest.raises(SpecError):
            module.Agent(ATARI_OBS, BOX, config)
        with pytest.raises(SpecError, match="uint8"):
            module.Agent(ArraySpec((84, 84, 4), "float32"), ATARI_ACTION, config)
    else:
        with pytest.raises(SpecError):
            module.Agent(LOWDIM_OBS, ATARI_ACTION, config)


@pytest.mark.parametrize(("name", "discrete"), sorted(AGENTS), ids=lambda x: str(x))
def test_paper_presets_build_and_act(name, discrete):
    kind = "atari" if discrete else "image"
    module = agent_module(name, discrete)
    for preset in [p for p in module.PRESETS if p.startswith("paper")]:
        obs_spec, action_spec = specs(kind)
        agent = make_agent(name, obs_spec, action_spec, preset=preset)
        if agent.batch_spec.statistics:  # what the loop does before the first update
            agent.set_statistics(fake_statistics(obs_spec, 0))
        a = agent.act(observation(kind, 2), is_first=np.ones(2, bool))
        assert a.shape == (2, *action_spec.shape)


def test_read_only_batches_are_accepted():
    for name, discrete, kind in [("dqn", True, "atari"), ("bc", False, "image")]:
        agent = build(name, discrete, kind)
        batch = batches(agent, kind, 1)[0]
        for array in (batch.observation, batch.next_observation, batch.action, batch.reward):
            for a in array.values() if isinstance(array, dict) else [array]:
                a.setflags(write=False)
        assert all(np.isfinite(v) for v in agent.update(batch).values())
