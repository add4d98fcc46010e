"""Every registered agent places every module, optimiser state, batch and random draw on its own
device, checked on a CPU-only machine in two ways, and its checkpoints cross devices.

- On ``meta`` (PyTorch's shape-only device): the agent built there must hold every parameter,
  buffer and optimiser state there and run its updates from numpy batches with every metric
  there; a module left on the CPU, a batch not brought to the device or a draw made on the CPU
  meets a meta tensor and fails. Acting must get as far as its one copy to the host
  (``.cpu()``, which meta cannot make).
- With torch's default device set to ``meta`` while a CPU agent updates and acts: a tensor an
  agent makes without naming its device (``torch.arange(n)``, ``torch.rand(..., generator=g)``)
  lands on meta and meets the agent's CPU tensors.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import common  # noqa: E402
from tests.agents.test_contract import CASES, IDS, batches, build, observation  # noqa: E402

META = torch.device("meta")
# Boolean-mask indexing has a data-dependent shape, which meta cannot compute.
META_CANNOT = {("rabm", False, "sequence")}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _tensors(agent):
    for m, module in agent.modules.items():
        for k, t in [*module.named_parameters(), *module.named_buffers()]:
            yield f"{m}.{k}", t


def _optimizer_states(agent):
    for name, opt in agent.optimizers.items():
        for state in opt.state.values():
            for key, value in state.items():
                # torch keeps the plain (non-fused) Adam's step counter on the CPU by design
                if isinstance(value, torch.Tensor) and key != "step":
                    yield f"{name}.{key}", value


@pytest.mark.parametrize(("name", "discrete", "kind"), CASES, ids=IDS)
def test_an_agent_built_for_a_device_lives_and_learns_there(name, discrete, kind, monkeypatch):
    if (name, discrete, kind) in META_CANNOT:
        pytest.skip("data-dependent shapes (boolean masks) have no meta implementation")
    metrics_devices = []

    def record(metrics):  # the one host synchronisation of an update, which meta cannot do
        metrics_devices.extend(v.device for v in metrics.values())
        return {k: 0.0 for k in metrics}

    monkeypatch.setattr(common, "metrics_to_floats", record)
    agent = build(name, discrete, kind, device=META)
    assert agent.device == META
    off = [k for k, t in _tensors(agent) if t.device != META]
    assert not off, f"{name}: not on the agent's device: {off}"
    # the optimisers hold the moved parameters themselves (built after the move)
    moved = {id(t) for _, t in _tensors(agent)}
    held = [p for o in agent.optimizers.values() for g in o.param_groups for p in g["params"]]
    assert held and all(id(p) in moved for p in held)
    for batch in batches(agent, kind):  # numpy batches, as the loop samples them
        agent.update(batch)
    assert metrics_devices and all(d == META for d in metrics_devices)
    states = list(_optimizer_states(agent))
    assert states and all(t.device == META for _, t in states)
    off = [k for k, t in _tensors(agent) if t.device != META]
    assert not off, f"{name}: moved off the device by an update: {off}"
    # acting runs on the device up to its one copy to the host, which meta cannot make (twice:
    # a recurrent agent's second step carries its state, reset where an episode starts)
    obs = observation(kind)
    for greedy, first in [(True, np.ones(5, bool)), (False, np.array([1, 0, 0, 1, 0], bool))]:
        with pytest.raises(NotImplementedError, match="Cannot copy out of meta tensor"):
            agent.act(obs, greedy=greedy, is_first=first, reward=np.ones(5))


@pytest.mark.parametrize(("name", "discrete", "kind"), CASES, ids=IDS)
def test_no_tensor_is_made_on_torchs_default_device(name, discrete, kind):
    agent = build(name, discrete, kind)
    data = batches(agent, kind, 2)
    agent.update(data[0])  # optimiser states are made on the first step
    obs, first = observation(kind), np.ones(5, bool)
    state = copy.deepcopy(agent.state_dict())  # a state_dict shares the live parameters
    expected = [agent.act(obs, greedy=g, is_first=first) for g in (True, False)]
    try:
        torch.set_default_device("meta")
        metrics = agent.update(data[1])
        acted = [agent.act(obs, greedy=g, is_first=first) for g in (True, False)]
    finally:
        torch.set_default_device(None)
    assert all(np.isfinite(v) for v in metrics.values())
    assert all(a.shape == e.shape for a, e in zip(acted, expected, strict=True))
    agent.load_state_dict(state)  # and the numbers are those of the default device's
    np.testing.assert_array_equal(agent.act(obs, greedy=True, is_first=first), expected[0])


def test_to_torch_moves_numpy_and_passes_tensors_already_there_untouched():
    x = np.arange(6, dtype=np.float64).reshape(2, 3)
    t = common.to_torch(x, META)
    assert t.device == META and t.dtype == torch.float32
    there = torch.zeros(3, device=META)
    assert common.to_torch(there, META) is there
    assert common.to_torch({"a": there}, META)["a"] is there
    cpu = torch.zeros(3, dtype=torch.int32)
    moved = common.to_torch(cpu, META, "int64")
    assert moved.device == META and moved.dtype == torch.int64
    assert common.to_torch(x).device.type == "cpu"  # no device: the CPU, as before


# --- checkpoints across devices ---------------------------------------------------------------
def _trained(name, discrete, kind, seed=0, **extra):
    agent = build(name, discrete, kind, seed=seed, **extra)
    for batch in batches(agent, kind, 2):
        agent.update(batch)
    return agent


FLAT = [(c, i) for c, i in zip(CASES, IDS, strict=True) if c[2] != "sequence"]


@pytest.mark.filterwarnings("ignore:for .* copying from a non-meta parameter:UserWarning")
@pytest.mark.parametrize(
    ("name", "discrete", "kind"), [c for c, _ in FLAT], ids=[i for _, i in FLAT]
)
def test_a_cpu_checkpoint_loads_into_an_agent_on_another_device(name, discrete, kind):
    state = _trained(name, discrete, kind).state_dict()
    other = build(name, discrete, kind, seed=5, device=META)
    other.load_state_dict(state)
    assert other.step == state["step"]
    assert all(t.device == META for _, t in _tensors(other))
    states = list(_optimizer_states(other))
    assert states and all(t.device == META for _, t in states)


def test_generators_saved_on_another_device_type_restart_from_the_checkpoint():
    """A checkpoint written on CUDA holds Philox generator states (16 bytes) a CPU generator
    cannot take: the modules, optimisers and step resume exactly, each generator restarts from
    a seed derived from its saved state (the same checkpoint, the same stream)."""
    agent = _trained("iqn", True, "atari")
    state = agent.state_dict()
    assert state["generator_devices"] == {"learner": "cpu", "act": "cpu"}
    foreign = {
        **state,
        "generators": {
            k: torch.arange(16, dtype=torch.uint8) + i for i, k in enumerate(state["generators"])
        },  # fmt: skip
        "generator_devices": {k: "cuda" for k in state["generators"]},
    }
    a, b = build("iqn", True, "atari", seed=1), build("iqn", True, "atari", seed=2)
    a.load_state_dict(foreign)
    b.load_state_dict(foreign)
    for k, v in agent.network.state_dict().items():
        assert torch.equal(a.network.state_dict()[k], v)
    assert a.step == agent.step
    for k in a.generators:
        assert torch.equal(a.generators[k].get_state(), b.generators[k].get_state())
        assert not torch.equal(a.generators[k].get_state(), agent.generators[k].get_state())
    assert not torch.equal(a.generators["learner"].get_state(), a.generators["act"].get_state())
    obs, first = observation("atari"), np.ones(5, bool)
    np.testing.assert_array_equal(a.act(obs, False, first), b.act(obs, False, first))
    # a checkpoint from before generator_devices was written on the CPU: it resumes exactly
    old = {k: v for k, v in state.items() if k != "generator_devices"}
    c = build("iqn", True, "atari", seed=3)
    c.load_state_dict(old)
    for k in c.generators:
        assert torch.equal(c.generators[k].get_state(), agent.generators[k].get_state())
