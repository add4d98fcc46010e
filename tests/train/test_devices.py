"""The training loop's runtime on the CPU: the prefetcher and the dataset held on the device give
the loop's own numbers, an interrupted run resumes exactly under another runtime, bf16 autocast
reaches the updates, and a checkpoint written on a GPU (its storages tagged ``cuda:0``, its
generators CUDA's) is evaluated and resumed on the CPU."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.devices import Runtime  # noqa: E402
from rlu.training.train import TrainConfig, train  # noqa: E402
from rlu.types import RluError  # noqa: E402
from tests.fakes import train_config  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
TASKS = {"dqn": "atari/Pong", "d4pg": "control_suite/cartpole_swingup"}
OVERRIDES = {
    "dqn": {"atari.batch_size": 8, "atari.channels": (4, 8, 8), "atari.hidden_size": 16,
            "atari.target_update_period": 2},
    "d4pg": {"batch_size": 8, "n_step": 3, "policy_layers": (16,), "critic_layers": (16,),
             "target_update_period": 2},
}  # fmt: skip


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    from rlu.data.store import Schema
    from rlu.data.synthetic import write_synthetic
    from rlu.tasks import get_task

    root = tmp_path_factory.mktemp("runtime_data")
    out = {}
    for agent, task in TASKS.items():
        schema = Schema.for_task(get_task(task))
        out[agent] = str(write_synthetic(root / agent, schema, 3, 30, vary_length=True))
    return out


def _config(agent, datasets, **runtime) -> TrainConfig:
    return train_config(
        task=TASKS[agent], agent=agent, dataset=datasets[agent], steps=6, eval_every=-1,
        log_every=1, checkpoint_every=3, torch_threads=1, overrides=OVERRIDES[agent],
        runtime=Runtime(**runtime),
    )  # fmt: skip


def _weights(run: Path, step: int = 6) -> dict[str, torch.Tensor]:
    state = torch.load(run / "checkpoints" / f"step_{step:08d}.pt", weights_only=True)
    return {f"{m}.{k}": v for m, sd in state["agent"]["modules"].items() for k, v in sd.items()}


def _same_run(a: Path, b: Path) -> None:
    assert (a / "metrics.jsonl").read_text() == (b / "metrics.jsonl").read_text()
    wa, wb = _weights(a), _weights(b)
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


@pytest.mark.parametrize("agent", sorted(TASKS))
def test_prefetch_and_data_on_device_give_the_loops_numbers(agent, datasets, tmp_path):
    train(_config(agent, datasets), tmp_path / "inline")
    train(_config(agent, datasets, prefetch=2), tmp_path / "prefetch")
    train(_config(agent, datasets, data_on_device=True), tmp_path / "on_device")
    train(_config(agent, datasets, data_on_device=True, prefetch=3), tmp_path / "both")
    for other in ("prefetch", "on_device", "both"):
        _same_run(tmp_path / "inline", tmp_path / other)
    saved = json.loads((tmp_path / "both" / "config.json").read_text())["train"]["run"]["runtime"]
    assert saved == {"device": "cpu", "precision": "fp32", "tf32": False, "compile": False,
                     "prefetch": 3, "data_on_device": True}  # fmt: skip


def test_an_interrupted_prefetching_run_resumes_exactly_under_another_runtime(
    datasets, tmp_path, monkeypatch
):
    """The prefetcher draws batches ahead of the learner; the checkpoint must hold the sampler
    as of the last batch the learner took. The 5th draw fails inside the prefetch thread; the
    learner gets the error in order (after 4 updates, the checkpoint at 3 written), and the run
    resumes on the dataset held on the device to the uninterrupted run's numbers."""
    import rlu.data.views as views

    train(_config("d4pg", datasets), tmp_path / "reference")
    calls = {"n": 0}
    sample = views.Sampler.sample

    def interrupted(self):
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return sample(self)

    monkeypatch.setattr(views.Sampler, "sample", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train(_config("d4pg", datasets, prefetch=2), tmp_path / "run")
    monkeypatch.setattr(views.Sampler, "sample", sample)
    lines = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(x)["step"] for x in lines] == [1, 2, 3, 4]
    train(_config("d4pg", datasets, data_on_device=True), tmp_path / "run", resume=True)
    _same_run(tmp_path / "reference", tmp_path / "run")


def test_bf16_autocast_reaches_the_updates(datasets, tmp_path):
    train(_config("d4pg", datasets), tmp_path / "fp32")
    train(_config("d4pg", datasets, precision="bf16"), tmp_path / "bf16")
    fp32, bf16 = (
        [json.loads(x) for x in (tmp_path / r / "metrics.jsonl").read_text().splitlines()]
        for r in ("fp32", "bf16")
    )
    assert all(np.isfinite(v) for m in bf16 for v in m.values())
    assert fp32[0]["critic/loss"] != bf16[0]["critic/loss"]  # the same batch, other arithmetic
    assert fp32[0]["critic/loss"] == pytest.approx(bf16[0]["critic/loss"], rel=0.05)
    weights = _weights(tmp_path / "bf16")
    assert all(v.dtype == torch.float32 for k, v in weights.items() if v.is_floating_point())


def test_resume_accepts_a_new_runtime_but_not_a_new_config(datasets, tmp_path):
    train(_config("dqn", datasets), tmp_path / "r")
    again = train(_config("dqn", datasets, prefetch=1), tmp_path / "r", resume=True)
    assert again["steps"] == 6  # finished: nothing to do, but no refusal either
    other = _config("dqn", datasets)
    other = dataclasses.replace(other, seed=1)
    with pytest.raises(RluError, match="different configuration"):
        train(other, tmp_path / "r", resume=True)


def test_tf32_on_the_cpu_and_data_on_device_for_sequences_are_refused(datasets, tmp_path):
    with pytest.raises(RluError, match="--tf32 applies to CUDA"):
        train(_config("dqn", datasets, tf32=True), tmp_path / "a")
    cfg = train_config(
        task=TASKS["d4pg"], agent="bc", dataset=datasets["d4pg"], steps=2, eval_every=-1,
        overrides={"recurrent": True, "hidden_size": 8, "num_layers": 2, "lstm_hidden": 4,
                   "sequence_length": 3, "batch_size": 4},
        runtime=Runtime(data_on_device=True),
    )  # fmt: skip
    with pytest.raises(RluError, match="Drop --data-on-device"):
        train(cfg, tmp_path / "b")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


# --- a checkpoint from a GPU, on the CPU -----------------------------------------------------
def _as_if_written_on_a_gpu(src: Path, dst: Path) -> None:
    """Re-save a checkpoint the way a CUDA run writes it: every storage tagged ``cuda:0`` (the
    tag torch.load restores to) and Philox generator states, which a CPU generator cannot take."""
    state = torch.load(src, weights_only=True)
    agent = state["agent"]
    agent["generators"] = {k: torch.arange(16, dtype=torch.uint8) for k in agent["generators"]}
    agent["generator_devices"] = {k: "cuda" for k in agent["generators"]}
    entry = (1, lambda obj: "cuda:0" if obj.device.type == "cpu" else None, lambda obj, loc: None)
    torch.serialization._package_registry.append(entry)
    torch.serialization._package_registry.sort(key=lambda e: e[0])
    try:
        torch.save(state, dst)
    finally:
        torch.serialization._package_registry.remove(entry)


def test_a_gpu_checkpoint_is_evaluated_and_resumed_on_the_cpu(datasets, tmp_path, monkeypatch):
    import rlu.data.views as views
    from rlu.training.checkpoints import load_state as load_checkpoint
    from rlu.training.restore import evaluate_run, load_agent

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU: the CPU side is what is checked here")
    run, cfg = tmp_path / "run", _config("dqn", datasets)
    sample = views.Sampler.sample
    calls = {"n": 0}

    def interrupted(self):  # the run stops after the checkpoint at step 3
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return sample(self)

    monkeypatch.setattr(views.Sampler, "sample", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, run)
    monkeypatch.setattr(views.Sampler, "sample", sample)
    ckpt = run / "checkpoints" / "step_00000003.pt"
    cpu_weights = _weights(run, 3)
    _as_if_written_on_a_gpu(ckpt, ckpt)
    with pytest.raises(RuntimeError, match="CUDA"):  # what torch.load alone does with it
        torch.load(ckpt, weights_only=True)
    assert load_checkpoint(ckpt)["step"] == 3
    agent, _ = load_agent(ckpt, device="cpu")
    for name, module in agent.modules.items():
        for k, v in module.state_dict().items():
            assert torch.equal(v, cpu_weights[f"{name}.{k}"])
    result = evaluate_run(ckpt, episodes=1, num_envs=1, max_steps=5, device="cpu")
    assert result.lengths == (5,)
    # resumed on the CPU from the same weights (the learner's random stream restarts)
    assert train(cfg, run, resume=True)["steps"] == 6
    steps = [json.loads(x)["step"] for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert steps == [1, 2, 3, 4, 5, 6]


def test_cli_device_errors_name_the_fix(datasets, tmp_path):
    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    args = [sys.executable, "-m", "rlu", "train", "--task", TASKS["dqn"], "--agent", "dqn",
            "--dataset", datasets["dqn"], "--steps", "1", "--out", str(tmp_path / "r"),
            "--device", "cuda"]  # fmt: skip
    res = subprocess.run(args, cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 2
    assert "sees no CUDA GPU" in res.stderr and "--device cpu" in res.stderr
    assert "Traceback" not in res.stderr
    res = subprocess.run([*args[:-1], "tpu"], cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 2 and "auto, cpu, cuda or cuda:N" in res.stderr
    assert not (tmp_path / "r").exists()


@pytest.mark.slow  # torch.compile's first updates compile (about a minute on a loaded CPU)
def test_compiled_modules_train_to_the_eager_numbers_within_rounding(datasets, tmp_path):
    from torch._dynamo.utils import counters

    counters.clear()
    train(_config("d4pg", datasets), tmp_path / "eager")
    assert counters["stats"]["unique_graphs"] == 0
    train(_config("d4pg", datasets, compile=True), tmp_path / "compiled")
    assert counters["stats"]["unique_graphs"] > 0  # the loop ran compiled forwards
    eager, compiled = (
        [json.loads(x) for x in (tmp_path / r / "metrics.jsonl").read_text().splitlines()]
        for r in ("eager", "compiled")
    )
    assert [m["step"] for m in compiled] == [m["step"] for m in eager]
    for a, b in zip(eager, compiled, strict=True):
        for k in a:
            assert b[k] == pytest.approx(a[k], rel=1e-3, abs=1e-5), (k, a, b)
    weights = _weights(tmp_path / "compiled")
    assert weights.keys() == _weights(tmp_path / "eager").keys()  # checkpoints unchanged
