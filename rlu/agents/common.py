"""The one helper stack of every agent, continuous or discrete: seeding, tensors, optimisers,
target networks, the checkpoint format and metrics. Pure functions, no agent logic.

Vocabulary (the same in every agent file): ``gamma`` is the agent's discount factor (a config
field), ``discount`` the per-step continuation of a batch (``rlu.types.Transition``);
``modules`` names every torch module an agent owns, ``optimizers`` every optimiser,
``generators`` every ``torch.Generator`` it draws from; ``step`` counts updates.

Checkpoint format (``agent_state``): ``{"modules": {name: state_dict}, "optimizers":
{name: state_dict}, "generators": {name: uint8 tensor}, "step": int}`` -- plain tensors, dicts
and numbers, so ``torch.load(..., weights_only=True)`` reads it.

Determinism: parameters are initialised under :func:`seeded` (a private copy of torch's global
RNG), every later draw goes through the agent's own generators, so building or training an agent
never touches (or depends on) the global RNG. On the CPU the same seed gives bit-identical numbers
for the same torch thread count.
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import numpy as np
import torch
from torch import nn

Metrics = dict[str, torch.Tensor]


def split_seed(seed: int, count: int) -> tuple[int, ...]:
    """``count`` independent 32-bit seeds from one (numpy's SeedSequence hashing)."""
    return tuple(int(s) for s in np.random.SeedSequence(int(seed)).generate_state(count))


@contextlib.contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Build modules under a private copy of torch's global RNG seeded with ``seed``; the
    caller's global RNG is left as it was."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        yield


def to_torch(x: Any) -> Any:
    """numpy (or a dict of numpy) -> tensors without copying where the dtype allows: float64
    becomes float32, uint8 frames stay uint8, read-only arrays (the store's views) are copied."""
    if isinstance(x, Mapping):
        return {k: to_torch(v) for k, v in x.items()}
    a = np.asarray(x)
    if a.dtype == np.float64:
        a = a.astype(np.float32)
    elif a.dtype == np.bool_ or not a.flags.writeable:
        a = a.copy()
    return torch.from_numpy(a)


def adam(params: Iterable[torch.Tensor], lr: float, eps: float = 1e-8) -> torch.optim.Adam:
    # fused CPU Adam: one kernel per step instead of one per tensor (measured in the bench).
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True)


def sgd_step(
    optimizer: torch.optim.Optimizer,
    loss: torch.Tensor,
    inputs: list[torch.Tensor] | None = None,
) -> None:
    """One gradient step on ``loss``; ``inputs`` limits the backward pass to those parameters
    (an actor loss that reads a critic leaves the critic's gradients alone)."""
    optimizer.zero_grad(set_to_none=True)
    loss.backward(inputs=inputs)
    optimizer.step()


def frozen_copy(module: nn.Module) -> nn.Module:
    """A target network: a deep copy that takes no gradients."""
    return copy.deepcopy(module).requires_grad_(False)


def hard_update(target: nn.Module, source: nn.Module) -> None:
    with torch.no_grad():
        torch._foreach_copy_(list(target.parameters()), list(source.parameters()))


def soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """Polyak averaging: target <- (1 - tau) target + tau source."""
    with torch.no_grad():
        torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)


def soft_updates(targets: Mapping[nn.Module, nn.Module], tau: float) -> None:
    """:func:`soft_update` of every ``{target: source}`` pair in one foreach call."""
    with torch.no_grad():
        torch._foreach_lerp_(
            [p for target in targets for p in target.parameters()],
            [p for source in targets.values() for p in source.parameters()],
            tau,
        )


def periodic_update(step: int, period: int, targets: Mapping[nn.Module, nn.Module]) -> None:
    """Hard-copy each source into its target every ``period`` steps (``{target: source}``)."""
    if period > 0 and step % period == 0:
        for target, source in targets.items():
            hard_update(target, source)


def learn(
    optimizer: torch.optim.Optimizer,
    loss: torch.Tensor,
    step: int,
    period: int = 0,
    targets: Mapping[nn.Module, nn.Module] | None = None,
) -> int:
    """One gradient step, then the hard target copies that fall due at the new step (every
    ``period`` steps, ``{target: source}``); returns the new step count."""
    sgd_step(optimizer, loss)
    step += 1
    periodic_update(step, period, targets or {})
    return step


def agent_state(
    modules: Mapping[str, nn.Module],
    optimizers: Mapping[str, torch.optim.Optimizer],
    generators: Mapping[str, torch.Generator],
    step: int,
) -> dict[str, Any]:
    """Everything an agent needs to resume (the checkpoint format in the module docstring)."""
    return {
        "modules": {k: m.state_dict() for k, m in modules.items()},
        "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
        "generators": {k: g.get_state() for k, g in generators.items()},
        "step": int(step),
    }


def load_agent_state(
    state: Mapping[str, Any],
    modules: Mapping[str, nn.Module],
    optimizers: Mapping[str, torch.optim.Optimizer],
    generators: Mapping[str, torch.Generator],
) -> int:
    """Restore what :func:`agent_state` saved; returns the step."""
    for k, m in modules.items():
        m.load_state_dict(state["modules"][k])
    for k, o in optimizers.items():
        o.load_state_dict(state["optimizers"][k])
    for k, g in generators.items():
        g.set_state(state["generators"][k])
    return int(state["step"])


def state_dict(agent: Any) -> dict[str, Any]:
    """An agent's ``state_dict``, shared as a function (``state_dict = common.state_dict`` in the
    class body): the checkpoint of its ``modules``, ``optimizers``, ``generators`` and ``step``."""
    return agent_state(agent.modules, agent.optimizers, agent.generators, agent.step)


def load_state_dict(agent: Any, state: Mapping[str, Any]) -> None:
    """An agent's ``load_state_dict`` (``load_state_dict = common.load_state_dict``)."""
    agent.step = load_agent_state(state, agent.modules, agent.optimizers, agent.generators)


def metrics_to_floats(metrics: Metrics) -> dict[str, float]:
    """The metrics as Python floats. On the CPU every tensor is ready when the update returns,
    so ``.item()`` per metric is the cheapest read (0.25 us each; stacking them first cost 15 us
    for five, measured); on an accelerator each ``.item()`` would wait for the device, so the
    metrics are stacked and read in one synchronisation."""
    if all(v.device.type == "cpu" for v in metrics.values()):
        return {k: float(v.item()) for k, v in metrics.items()}
    keys = list(metrics)
    values = torch.stack([metrics[k].detach().float().reshape(()) for k in keys]).tolist()
    return dict(zip(keys, (float(v) for v in values), strict=True))
