"""The test agent of fake_agent.py with a hidden layer: a second agent name for sweeps."""

from __future__ import annotations

from tests.train.fake_agent import Agent, Config

__all__ = ["Agent", "Config", "GRID", "PRESETS"]

PRESETS = {"small": Config(hidden=16), "paper": Config(hidden=64)}
GRID = {"learning_rate": [1e-2, 3e-3]}
