"""A small real PyTorch agent following the agent-module convention (Config, Agent, PRESETS,
GRID), for the training-loop tests: behaviour cloning with a linear (or one-hidden-layer) policy
and Gaussian input noise drawn from the agent's own generator, so an exact resume must restore
that generator, the optimiser and the weights."""

from __future__ import annotations

import dataclasses
import os
import signal
import threading
from collections.abc import Mapping

import numpy as np
import torch

from rlu.devices import resolve_device
from rlu.types import BatchSpec, BoundedSpec


@dataclasses.dataclass(frozen=True)
class Config:
    learning_rate: float = 1e-2
    """Adam learning rate."""
    batch_size: int = 64
    """Transitions per update."""
    num_steps: int = 200
    """Learner steps of a full run (the loop's default)."""
    hidden: int = 0
    """Hidden units (0: a linear policy)."""
    input_noise: float = 0.05
    """Std of Gaussian noise added to observations during updates."""


PRESETS = {"small": Config(), "paper": Config(hidden=64)}
GRID = {"learning_rate": [1e-2, 3e-3]}


def _flat(obs, device) -> torch.Tensor:
    if isinstance(obs, Mapping):
        parts = [_numpy(obs[k]).reshape(len(obs[k]), -1) for k in sorted(obs)]
        return torch.from_numpy(np.concatenate(parts, axis=1)).to(device)
    return torch.from_numpy(_numpy(obs).reshape(len(obs), -1)).to(device)


def _numpy(x) -> np.ndarray:  # the loop may hand over tensors (prefetched, or on the device)
    return (x.cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)).astype(np.float32)


class Agent:
    def __init__(
        self, observation_spec, action_spec: BoundedSpec, config: Config, seed: int = 0,
        device="cpu",
    ):  # fmt: skip
        self.config, self.spec, self.device = config, action_spec, resolve_device(device)
        self.batch_spec = BatchSpec(config.batch_size)
        self.pretrain_steps = 0
        self.num_steps = config.num_steps
        obs_dim = sum(s.size for s in observation_spec.values())
        act_dim = action_spec.size
        self.gen = torch.Generator().manual_seed(seed)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            if config.hidden:
                self.net = torch.nn.Sequential(
                    torch.nn.Linear(obs_dim, config.hidden),
                    torch.nn.Tanh(),
                    torch.nn.Linear(config.hidden, act_dim),
                )
            else:
                self.net = torch.nn.Linear(obs_dim, act_dim)
        self.net.to(self.device)
        self.opt = torch.optim.Adam(self.net.parameters(), lr=config.learning_rate)
        self.modules = {"net": self.net}
        self.scale = float(action_spec.maximum)

    def _forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.scale * torch.tanh(self.net(x))

    def update(self, batch) -> dict[str, float]:
        # test hook: the process SIGKILLs itself at its N-th update (a crash at a chosen step)
        self._updates = getattr(self, "_updates", 0) + 1
        if self._updates == int(os.environ.get("RLU_TEST_SIGKILL_AT_UPDATE", "0")):
            os.kill(os.getpid(), signal.SIGKILL)
        # test hook: the process writes its pid into this FIFO at its first update, then hangs
        if self._updates == 1 and os.environ.get("RLU_TEST_HOLD_FIFO"):
            with open(os.environ["RLU_TEST_HOLD_FIFO"], "w") as fifo:
                fifo.write(f"{os.getpid()}\n")
            threading.Event().wait()
        x = _flat(batch.observation, self.device)
        x = x + self.config.input_noise * torch.randn(x.shape, generator=self.gen).to(x.device)
        target = torch.from_numpy(_numpy(batch.action).reshape(len(x), -1)).to(self.device)
        loss = torch.nn.functional.mse_loss(self._forward(x), target)
        self.opt.zero_grad()
        loss.backward()
        self.opt.step()
        return {"actor/bc_loss": float(loss.detach())}

    def act(self, observation, greedy: bool = True, is_first=None, reward=None) -> np.ndarray:
        with torch.no_grad():
            a = self._forward(_flat(observation, self.device)).cpu().numpy()
        return a.reshape(len(a), *self.spec.shape).astype(self.spec.dtype)

    def state_dict(self) -> dict:
        return {
            "net": self.net.state_dict(),
            "opt": self.opt.state_dict(),
            "gen": self.gen.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.net.load_state_dict(state["net"])
        self.opt.load_state_dict(state["opt"])
        self.gen.set_state(state["gen"])
