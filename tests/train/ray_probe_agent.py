"""The test agent of fake_agent.py, reporting the resources Ray gave its run as metrics
(``probe/gpus``, ``probe/cpus``; 0 outside Ray), so a sweep's own runs show what they asked for."""

from __future__ import annotations

from tests.train.fake_agent import GRID, PRESETS, Config
from tests.train.fake_agent import Agent as _FakeAgent

__all__ = ["Agent", "Config", "GRID", "PRESETS"]


class Agent(_FakeAgent):
    def update(self, batch) -> dict[str, float]:
        import ray

        metrics = super().update(batch)
        got = ray.get_runtime_context().get_assigned_resources() if ray.is_initialized() else {}
        return {**metrics, "probe/gpus": got.get("GPU", 0.0), "probe/cpus": got.get("CPU", 0.0)}
