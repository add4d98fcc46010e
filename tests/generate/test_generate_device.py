"""Generation on a device: ``--device`` reaches the behaviour agents, and a run whose saved state
was written on a GPU (storages tagged ``cuda:0``) resumes on the CPU to the same bytes."""

from __future__ import annotations

import pytest

from tests.generate.test_generate import TASK, _files

torch = pytest.importorskip("torch")
pytest.importorskip("dm_control")


def _retag_as_cuda(path) -> None:
    """Re-save ``path`` as a CUDA process writes it: every storage tagged ``cuda:0``."""
    state = torch.load(path, weights_only=True)
    entry = (1, lambda obj: "cuda:0" if obj.device.type == "cpu" else None, lambda o, loc: None)
    torch.serialization._package_registry.append(entry)
    torch.serialization._package_registry.sort(key=lambda e: e[0])
    try:
        torch.save(state, path)
    finally:
        torch.serialization._package_registry.remove(entry)


def test_device_reaches_the_behaviour_agents(tmp_path, monkeypatch):
    import rlu.generate.online as online
    from rlu.generate import GenerateConfig, generate
    from rlu.workers import Backend

    asked = []
    make = online.make_behaviour_agent

    def recording(task, cfg, seed, device="cpu"):  # builds on the CPU: no GPU here
        asked.append(device)
        return make(task, cfg, seed, "cpu")

    monkeypatch.setattr(online, "make_behaviour_agent", recording)
    # workers=1: the runs play in this process, where the patch is
    config = GenerateConfig(
        TASK,
        scale="tiny",
        runs=2,
        seed=1,
        device="cuda:1",
        backend=Backend(workers=1),
        progress=False,
    )
    generate(config, tmp_path / "d")
    assert asked == ["cuda:1", "cuda:1"]


def test_a_run_saved_on_a_gpu_resumes_on_the_cpu(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU: the CPU side is what is checked here")
    from rlu.generate import GenerateConfig, generate

    config = GenerateConfig(TASK, scale="tiny", runs=1, seed=7, progress=False)
    ref = generate(config, tmp_path / "ref")

    def stop(run, chunk):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        generate(config, tmp_path / "out", on_chunk=stop)
    state = tmp_path / ".out.generate" / "run_000" / "state.pt"
    _retag_as_cuda(state)
    with pytest.raises(RuntimeError, match="CUDA"):
        torch.load(state, weights_only=True)
    assert _files(generate(config, tmp_path / "out")) == _files(ref)
