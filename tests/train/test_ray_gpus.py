"""GPU requests on Ray, checked on a local Ray instance that declares one (logical) GPU: no GPU
is needed to see what a run asks for and gets. Four runs asking for 0.25 GPU each run at the
same time on the one GPU; a sweep's runs get the share they asked for; requests Ray could never
schedule, or CUDA without a GPU request, are refused before anything is submitted."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rlu.devices import Runtime, check_ray_gpus, ray_options
from rlu.types import RluError

ray = pytest.importorskip("ray")
pytest.importorskip("torch")


@pytest.fixture(scope="module")
def one_gpu_ray():
    if ray.is_initialized():
        pytest.skip("a Ray instance is already running in this process")
    # address="local": a new instance, even where a Ray cluster already runs on this machine
    ray.init(address="local", num_cpus=4, num_gpus=1, include_dashboard=False,
             log_to_driver=False)  # fmt: skip
    yield ray
    ray.shutdown()


def test_four_quarter_gpu_runs_share_one_gpu_at_once(one_gpu_ray):
    @ray.remote
    class Barrier:
        """Lets its callers through only once ``n`` of them are inside at the same time."""

        def __init__(self, n):
            import asyncio

            self.n, self.inside, self.open = n, 0, asyncio.Event()

        async def wait(self):
            self.inside += 1
            if self.inside == self.n:
                self.open.set()
            await self.open.wait()
            return self.inside

    def probe(barrier):
        import os

        got = ray.get_runtime_context().get_assigned_resources()
        together = ray.get(barrier.wait.remote())
        return got, ray.get_gpu_ids(), os.environ.get("CUDA_VISIBLE_DEVICES"), together

    barrier = Barrier.remote(4)
    remote = ray.remote(**ray_options(0.25))(probe)
    # 4 x 0.25 fit the one GPU at once: every run passes the barrier (a run asking for more,
    # or a whole GPU, would leave the others waiting; the timeout only ends such a deadlock)
    results = ray.get([remote.remote(barrier) for _ in range(4)], timeout=300)
    for got, gpu_ids, visible, together in results:
        assert got == {"CPU": 1.0, "GPU": 0.25}
        assert [str(g) for g in gpu_ids] == ["0"] and visible == "0"
        assert together == 4


def test_requests_ray_cannot_serve_are_refused_first(one_gpu_ray):
    with pytest.raises(RluError, match="has 1 GPU"):
        check_ray_gpus(ray, 2, "auto")
    with pytest.raises(RluError, match="needs --gpus-per-run"):
        check_ray_gpus(ray, 0, "cuda:0")
    check_ray_gpus(ray, 0.5, "cuda")
    check_ray_gpus(ray, 0, "cpu")


def test_a_sweeps_runs_get_the_gpu_share_they_ask_for(one_gpu_ray, pendulum_datasets, tmp_path):
    from rlu.training.sweep import sweep
    from rlu.workers import Backend
    from tests.fakes import sweep_config

    config = sweep_config(
        tasks=("test/pendulum",), agents=("tests.train.ray_probe_agent",),
        datasets={"test/pendulum": pendulum_datasets["test/pendulum"]}, seeds=(0, 1), steps=4,
        eval_episodes=1, eval_envs=1,
        eval_max_steps=5, log_every=1, checkpoint_every=4, max_configs=1,
        env="tests.train.pendulum:make_env", runtime=Runtime(device="auto"),
    )  # fmt: skip
    records = sweep(config, tmp_path / "s", Backend("ray", gpus_per_job=0.5))
    assert len(records) == 2
    for r in records:
        lines = (Path(r["run"]) / "metrics.jsonl").read_text().splitlines()
        assert {(m["probe/gpus"], m["probe/cpus"]) for m in map(json.loads, lines)} == {(0.5, 1.0)}
    with pytest.raises(RluError, match="has 1 GPU"):
        sweep(config, tmp_path / "s", Backend("ray", gpus_per_job=3))
    with pytest.raises(RluError, match="--backend ray"):
        Backend("local", gpus_per_job=0.5)


def test_generation_checks_its_gpu_request_before_any_run(one_gpu_ray, tmp_path):
    from rlu.generate import GenerateConfig, generate
    from rlu.workers import Backend

    config = GenerateConfig("atari/Pong", scale="tiny", backend=Backend("ray", gpus_per_job=2))
    with pytest.raises(RluError, match="has 1 GPU"):
        generate(config, tmp_path / "g")
    with pytest.raises(RluError, match="--backend ray"):
        GenerateConfig("atari/Pong", scale="tiny", backend=Backend(gpus_per_job=0.5))
    assert not (tmp_path / "g").exists()  # no dataset
