"""Device strings and the runtime options (rlu.devices.resolve_device, rlu.devices): what they
decide on this machine, and, with PyTorch's CUDA queries answered as on a 2-GPU machine, what
they would decide there. No GPU is needed: the CUDA side of the answers is the only stand-in."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from rlu.devices import (  # noqa: E402
    Runtime,
    check_gpus_per_run,
    compile_modules,
    numerics,
    ray_options,
    resolve_device,
)
from rlu.types import RluError  # noqa: E402

CPU = torch.device("cpu")


@pytest.fixture
def two_gpus(monkeypatch):
    """PyTorch's answers on a machine with two CUDA GPUs (only the queries, nothing runs)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: True)


def test_cpu_and_auto_on_a_machine_without_cuda():
    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU: auto picks it")
    assert resolve_device("cpu") == CPU
    assert resolve_device(" CPU ") == CPU
    assert resolve_device("auto") == CPU
    meta = torch.device("meta")
    assert resolve_device(meta) is meta  # a torch.device passes through


@pytest.mark.parametrize("text", ["cuda", "cuda:0", "cuda:1"])
def test_cuda_without_cuda_names_the_fix(text):
    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    with pytest.raises(RluError, match=r"sees no CUDA GPU.*--device cpu"):
        resolve_device(text)


@pytest.mark.parametrize("text", ["gpu", "cuda:x", "cuda:", "tpu:0", "", None, 3, "cpu:0"])
def test_unknown_device_strings_list_the_choices(text):
    with pytest.raises(RluError, match=r"auto, cpu, cuda or cuda:N"):
        resolve_device(text)


def test_auto_and_cuda_on_a_two_gpu_machine(two_gpus):
    assert resolve_device("auto") == torch.device("cuda", 0)
    assert resolve_device("cuda") == torch.device("cuda", 0)
    assert resolve_device("CUDA:1") == torch.device("cuda", 1)
    with pytest.raises(RluError, match=r"sees 2 CUDA GPU\(s\).*cuda:0 \.\. cuda:1"):
        resolve_device("cuda:2")


def test_runtime_resolves_device_and_prefetch_per_device(two_gpus):
    assert Runtime().resolve() == Runtime(device="cpu", prefetch=0)
    cuda = Runtime(device="auto", precision="bf16", tf32=True).resolve()
    assert (cuda.device, cuda.prefetch, cuda.tf32) == ("cuda:0", 2, True)
    assert Runtime(device="cuda:1", prefetch=0).resolve().prefetch == 0  # an explicit 0 stays
    assert Runtime.from_json(cuda.to_json()) == cuda


def test_runtime_refuses_what_the_device_cannot_do(two_gpus, monkeypatch):
    with pytest.raises(RluError, match="--tf32 applies to CUDA"):
        Runtime(device="cpu", tf32=True).resolve()
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: False)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda *a: "Tesla V100")
    with pytest.raises(RluError, match="V100.*no bfloat16"):
        Runtime(device="cuda", precision="bf16").resolve()


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [("precision", "fp16", "fp32, bf16"), ("prefetch", -1, "an integer from 0 to 64"),
     ("prefetch", True, "a boolean"), ("prefetch", 1.5, "an integer from 0 to 64"),
     ("prefetch", 65, "'prefetch' is 65; expected an integer from 0 to 64")],
)  # fmt: skip
def test_runtime_fields_are_checked(field, value, match):
    with pytest.raises(RluError, match=match):
        Runtime(**{field: value})


def test_bf16_autocast_applies_to_updates_only():
    """Under the runtime's update context a matmul runs in bfloat16; outside it, in fp32."""
    a = torch.ones(4, 4)
    with numerics(Runtime(precision="bf16").resolve()) as update_context:
        with update_context():
            assert (a @ a).dtype == torch.bfloat16
        assert (a @ a).dtype == torch.float32
    with numerics(Runtime().resolve()) as update_context, update_context():
        assert (a @ a).dtype == torch.float32


def test_bf16_forwards_after_an_optimiser_step_read_the_stepped_weights():
    """An update steps one network, then reads it again (IQL's V, BCQ's critic): under the
    update context that second forward must see the new weights, not a bf16 copy cached
    before the step (autocast's weight cache, which lasts the whole context)."""
    from torch import nn

    from rlu.agents import common

    torch.manual_seed(0)
    net = nn.Linear(8, 4)
    x = torch.randn(16, 8)
    opt = common.adam(net.parameters(), lr=0.1)
    with numerics(Runtime(precision="bf16").resolve()) as update_context, update_context():
        before = net(x)
        common.sgd_step(opt, before.float().square().mean())
        after = net(x)
    with torch.no_grad():
        expected = nn.functional.linear(x, net.weight, net.bias)  # fp32, the stepped weights
    assert not torch.equal(after, before)
    torch.testing.assert_close(after.float(), expected, rtol=2e-2, atol=2e-2)


@pytest.mark.parametrize("gpus", [0, 0.25, 0.5, 1, 2, 4.0])
def test_gpu_requests_fractions_and_whole_gpus(gpus):
    assert check_gpus_per_run(gpus) == gpus
    assert ray_options(gpus) == ({"num_cpus": 1, "num_gpus": gpus} if gpus else {"num_cpus": 1})


@pytest.mark.parametrize("gpus", [-0.5, 1.5, float("nan")])
def test_gpu_requests_ray_cannot_schedule_are_refused(gpus):
    with pytest.raises(RluError, match="fraction in"):
        check_gpus_per_run(gpus)


def test_compile_wraps_forwards_in_place_and_keeps_the_checkpoint_keys():
    from rlu.agents import make_agent
    from tests.agents.test_contract import BOX
    from tests.fakes import LOWDIM_OBS

    agent = make_agent("bc", LOWDIM_OBS, BOX, hidden_size=8, num_layers=2)
    keys = {k: list(m.state_dict()) for k, m in agent.modules.items()}
    # the policy is a ModuleDict (no forward): its torso and head are compiled instead
    assert compile_modules(agent.modules) == ["policy.torso", "policy.head"]
    assert {k: list(m.state_dict()) for k, m in agent.modules.items()} == keys
    assert agent.modules["policy"]["torso"]._compiled_call_impl is not None


def test_tf32_is_set_for_a_cuda_run_and_restored_after():
    """The CUDA branch sets process-wide flags (they exist on a CPU build too)."""
    before = (torch.get_float32_matmul_precision(), torch.backends.cudnn.allow_tf32)
    with numerics(Runtime(device="cuda:0", tf32=True, prefetch=2)):
        assert torch.get_float32_matmul_precision() == "high" and torch.backends.cudnn.allow_tf32
    assert (torch.get_float32_matmul_precision(), torch.backends.cudnn.allow_tf32) == before
    with numerics(Runtime(device="cuda:0", prefetch=2)):  # fp32 means fp32, convolutions too
        assert torch.get_float32_matmul_precision() == "highest"
        assert not torch.backends.cudnn.allow_tf32
    assert (torch.get_float32_matmul_precision(), torch.backends.cudnn.allow_tf32) == before
