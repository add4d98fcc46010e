"""The contract every continuous agent meets (d3rlpy's contract test), on fake specs.

Cases: every continuous agent on low-dimensional dict observations and on features + a camera
image; the recurrent agents (BC, RABM with ``recurrent=True``) on sequence windows. Networks are
shrunk so the whole file runs in seconds; the code paths are the presets' own.
"""

from __future__ import annotations

import io

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import CONTINUOUS_AGENTS, agent_module, make_agent  # noqa: E402
from rlu.types import BoundedSpec  # noqa: E402
from tests.fakes import IMAGE_OBS, LOWDIM_OBS, fake_sequence, fake_transition  # noqa: E402

# An off-centre box, so the [-1, 1] <-> spec mapping is exercised too.
ACTION = BoundedSpec((3,), "float32", -2.0, 0.5)

# Tiny networks; target periods and BRAC's behaviour phase short enough that three updates
# reach every parameter (targets included).
TINY = {
    "bc": dict(hidden_size=32, num_layers=2, lstm_hidden=16, sequence_length=5),
    "d4pg": dict(policy_layers=(32, 32), critic_layers=(32, 32), torso_hidden=16,
                 target_update_period=2),
    "bcq": dict(actor_layers=(32,), critic_layers=(32,), vae_layers=(32,), torso_hidden=16),
    "brac": dict(policy_layers=(32,), critic_layers=(32,), behaviour_layers=(32,),
                 torso_hidden=16, behaviour_steps=1),
    "rabm": dict(hidden_size=32, num_layers=2, lstm_hidden=16, sequence_length=5,
                 target_update_period=2, num_samples=4),
}  # fmt: skip
RECURRENT = ("bc", "rabm")
CASES = [(n, "lowdim") for n in CONTINUOUS_AGENTS] + [(n, "image") for n in CONTINUOUS_AGENTS]
CASES += [(n, "sequence") for n in RECURRENT]
UPDATES = 3


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    # Tiny tensors: intra-op threads only add synchronisation (many times slower on a busy CPU).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def build(name: str, kind: str, seed: int = 0):
    spec = IMAGE_OBS if kind == "image" else LOWDIM_OBS
    overrides = dict(TINY[name])
    if kind == "sequence":
        overrides["recurrent"] = True
    return make_agent(name, spec, ACTION, seed=seed, **overrides), spec


def batches(agent, spec, kind: str):
    if kind == "sequence":
        return [fake_sequence(spec, ACTION, batch=4, length=5, seed=i) for i in range(UPDATES)]
    return [fake_transition(spec, ACTION, batch=8, seed=i) for i in range(UPDATES)]


def parameters(agent) -> dict[str, torch.Tensor]:
    return {
        f"{m}.{k}": p.detach().clone()
        for m, module in agent.modules.items()
        for k, p in module.named_parameters()
    }


def observation(spec, n: int = 4):
    return fake_transition(spec, ACTION, batch=n, seed=99).observation


def test_every_continuous_agent_is_registered_with_presets_and_grid():
    assert set(CONTINUOUS_AGENTS) == {"bc", "d4pg", "bcq", "brac", "rabm"}
    for name in CONTINUOUS_AGENTS:
        module = agent_module(name, discrete=False)
        assert set(module.PRESETS) >= {"paper", "small"}
        assert module.Config is type(module.PRESETS["paper"])
        assert module.PRESETS["paper"] == module.Config()  # the paper preset is the defaults
        fields = set(module.Config.__dataclass_fields__)
        assert set(module.GRID) <= fields
        assert module.Agent.__name__.lower().startswith(name)


@pytest.mark.parametrize("name,kind", CASES)
def test_update_gives_metrics_to_floats_and_moves_every_parameter(name, kind):
    agent, spec = build(name, kind)
    assert agent.batch_kind == ("sequence" if kind == "sequence" else "transition")
    before = parameters(agent)
    for batch in batches(agent, spec, kind):
        metrics = agent.update(batch)
    assert metrics and all(isinstance(v, float) and np.isfinite(v) for v in metrics.values())
    assert all("/" in k for k in metrics), metrics
    after = parameters(agent)
    frozen = [k for k in before if torch.equal(before[k], after[k])]
    assert not frozen, f"{name}: parameters never changed: {frozen}"


@pytest.mark.parametrize("name,kind", CASES)
def test_actions_lie_inside_the_action_spec(name, kind):
    agent, spec = build(name, kind)
    for batch in batches(agent, spec, kind):
        agent.update(batch)
    obs = observation(spec, 6)
    for greedy in (True, False):
        getattr(agent, "reset", lambda: None)()
        a = agent.act(obs, greedy=greedy)
        assert a.shape == (6, *ACTION.shape) and a.dtype == np.float32
        assert np.all(a >= ACTION.minimum) and np.all(a <= ACTION.maximum)
        assert np.all(np.isfinite(a))


@pytest.mark.parametrize("name,kind", CASES)
def test_state_dict_round_trip_keeps_greedy_actions_and_resumes_identically(name, kind):
    agent, spec = build(name, kind, seed=0)
    data = batches(agent, spec, kind)
    agent.update(data[0])
    buffer = io.BytesIO()
    torch.save(agent.state_dict(), buffer)
    buffer.seek(0)
    state = torch.load(buffer, weights_only=True)  # plain tensors and containers only

    other, _ = build(name, kind, seed=123)
    other.load_state_dict(state)
    obs = observation(spec)
    for a in (agent, other):
        getattr(a, "reset", lambda: None)()
    np.testing.assert_array_equal(agent.act(obs), other.act(obs))
    # Networks, optimisers, step counters and RNG state all travel: the next update matches.
    assert agent.update(data[1]) == other.update(data[1])
    np.testing.assert_array_equal(agent.act(obs, greedy=False), other.act(obs, greedy=False))


@pytest.mark.parametrize("name,kind", CASES)
def test_same_seed_same_numbers_other_seed_other_numbers(name, kind):
    runs = []
    for seed in (7, 7, 8):
        agent, spec = build(name, kind, seed=seed)
        metrics = [agent.update(b) for b in batches(agent, spec, kind)]
        getattr(agent, "reset", lambda: None)()
        runs.append((metrics, agent.act(observation(spec))))
    assert runs[0][0] == runs[1][0]
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    assert runs[0][0] != runs[2][0]


def test_building_and_training_leave_the_global_torch_rng_alone():
    torch.manual_seed(0)
    expected = torch.rand(3)
    torch.manual_seed(0)
    agent, spec = build("bcq", "lowdim")
    for b in batches(agent, spec, "lowdim"):
        agent.update(b)
    agent.act(observation(spec), greedy=False)
    assert torch.equal(torch.rand(3), expected)


@pytest.mark.parametrize("name", CONTINUOUS_AGENTS)
def test_paper_presets_build_with_the_paper_sizes_and_act_on_images(name):
    module = agent_module(name, discrete=False)
    for preset in [p for p in module.PRESETS if p.startswith("paper")]:
        agent = make_agent(name, IMAGE_OBS, ACTION, preset=preset)
        a = agent.act(observation(IMAGE_OBS, 2))
        assert a.shape == (2, 3) and np.all((a >= ACTION.minimum) & (a <= ACTION.maximum))
    if name in ("bc", "rabm"):
        mlp = (agent.policy["torso"] if name == "bc" else agent.policy.torso).mlp
        assert len(mlp.blocks) * 2 == 8 and mlp.output_dim == 1024
        assert agent.batch_kind == "sequence"  # the last preset built is paper_recurrent
