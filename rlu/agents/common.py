"""The one helper stack of every agent, continuous or discrete: seeding, tensors, optimisers,
target networks, the checkpoint format and metrics. Pure functions, no agent logic.

Vocabulary (the same in every agent file): ``gamma`` is the agent's discount factor (a config
field), ``discount`` the per-step continuation of a batch (``rlu.types.Transition``);
``modules`` names every torch module an agent owns, ``optimizers`` every optimiser,
``generators`` every ``torch.Generator`` it draws from; ``step`` counts updates.

Checkpoint format (``agent_state``): ``{"modules": {name: state_dict}, "optimizers":
{name: state_dict}, "generators": {name: uint8 tensor}, "generator_devices": {name: device
type}, "step": int}`` -- plain tensors, dicts and numbers, so ``torch.load(...,
weights_only=True)`` reads it. It loads on any device (``rlu.training.runs`` maps it to the CPU,
then ``load_state_dict`` copies into the agent's own device).

Devices (docs/devices.md): an agent takes ``device`` ("cpu", "cuda", "cuda:N", "auto" or a
``torch.device``) and resolves it once with :func:`device`; its parameters are initialised on
the CPU under :func:`seeded` (the same initial weights on every device) and then moved, before
its optimisers are built; its generators live on its device (:func:`generator`) and every draw
names the device of the tensors it joins; :func:`to_torch` brings batches and observations to
the device and passes tensors already there through; results leave with ``.cpu()``.

Determinism: parameters are initialised under :func:`seeded` (a private copy of torch's global
RNG), every later draw goes through the agent's own generators, so building or training an agent
never touches (or depends on) the global RNG. On the CPU the same seed gives bit-identical numbers
for the same torch thread count.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import Any, NamedTuple, TypeVar

import numpy as np
import torch
from torch import nn

from rlu.devices import resolve_device
from rlu.types import RluError

Metrics = dict[str, torch.Tensor]
LSTMState = tuple[torch.Tensor, ...]
"""An ``nn.LSTM``'s (h, c) state, (layers, B, H) each."""
TensorObservation = torch.Tensor | Mapping[str, torch.Tensor]
"""An observation batch as tensors: one tensor, or a dict of them (``to_torch`` of an
``rlu.types.Observation``)."""
_Module = TypeVar("_Module", bound=nn.Module)


@contextlib.contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Build modules under a private copy of torch's global RNG seeded with ``seed``; the
    caller's global RNG is left as it was."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        yield


def device(spec: Any = "cpu") -> torch.device:
    """An agent's device, resolved once in its ``__init__`` (``rlu.devices.resolve_device``: an
    unknown or missing device is an ``RluError`` naming the fix)."""
    return resolve_device(spec)


def generator(seed: int, device: torch.device) -> torch.Generator:
    """A generator seeded with ``seed`` on ``device``, so draws happen where the tensors they
    join live. A device without generators (``meta``, the placement tests') gets a CPU one."""
    if device.type in ("cpu", "meta"):
        return torch.Generator().manual_seed(int(seed))
    return torch.Generator(device=device).manual_seed(int(seed))


_DTYPES = {"int64": (np.int64, torch.int64), "float32": (np.float32, torch.float32)}


def to_torch(x: Any, device: torch.device | None = None, dtype: str | None = None) -> Any:
    """numpy (or a dict of numpy) -> tensors on ``device`` (None: the CPU), without copying on
    the CPU where the dtype allows: float64 becomes float32, uint8 frames stay uint8, read-only
    arrays (the store's views) are copied; ``dtype`` ('int64', 'float32') casts first. A tensor
    already on ``device`` with the dtype passes through untouched (batches the loop prepared)."""
    if isinstance(x, Mapping):
        return {k: to_torch(v, device, dtype) for k, v in x.items()}
    if isinstance(x, torch.Tensor):
        if dtype is not None:
            x = x.to(_DTYPES[dtype][1])
        return x if device is None or x.device == device else x.to(device)
    a = np.asarray(x) if dtype is None else np.asarray(x, _DTYPES[dtype][0])
    if a.dtype == np.float64:
        a = a.astype(np.float32)
    elif a.dtype == np.bool_ or not a.flags.writeable:
        a = a.copy()
    t = torch.from_numpy(a)
    return t if device is None or device.type == "cpu" else t.to(device)


class TorchTransition(NamedTuple):
    """A :class:`rlu.types.Transition` as tensors on the agent's device, what the losses take:
    a continuous agent's action mapped into [-1, 1] by its ``networks.ActionScaler``
    (:func:`transition`), a discrete agent's observations as ``discrete_common.frames`` gives
    them (``discrete_common.to_torch``)."""

    observation: TensorObservation
    action: torch.Tensor
    reward: torch.Tensor
    discount: torch.Tensor
    next_observation: TensorObservation


def transition(batch: Any, scaler: Any, device: torch.device) -> TorchTransition:
    """A Transition batch as :class:`TorchTransition` (:func:`to_torch` on every field)."""
    return TorchTransition(
        observation=to_torch(batch.observation, device),
        action=scaler.to_unit(to_torch(batch.action, device)),
        reward=to_torch(batch.reward, device),
        discount=to_torch(batch.discount, device),
        next_observation=to_torch(batch.next_observation, device),
    )


def adam(params: Iterable[torch.Tensor], lr: float, eps: float = 1e-8) -> torch.optim.Adam:
    # fused Adam: one kernel per step instead of one per tensor (measured in the bench, CPU);
    # devices without the fused kernel (meta, the placement tests') take the plain one
    params = list(params)
    fused = all(p.device.type in ("cpu", "cuda") for p in params)
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=fused or None)


def sgd_step(
    optimizer: torch.optim.Optimizer,
    loss: torch.Tensor,
    inputs: Sequence[torch.Tensor] | None = None,
    max_norm: float = 0.0,
) -> None:
    """One gradient step on ``loss``; ``inputs`` limits the backward pass to those parameters
    (an actor loss that reads a critic leaves the critic's gradients alone). ``max_norm`` > 0
    first clips the gradient of the optimiser's parameters to that global norm (Acme's
    ``tf.clip_by_global_norm``)."""
    optimizer.zero_grad(set_to_none=True)
    kind = loss.device.type
    if torch.amp.is_autocast_available(kind) and torch.is_autocast_enabled(kind):
        # the loop's bf16 autocast covers forward passes only
        with torch.autocast(kind, enabled=False):
            _backward_step(optimizer, loss, inputs, max_norm)
        return
    _backward_step(optimizer, loss, inputs, max_norm)


def _backward_step(
    optimizer: torch.optim.Optimizer,
    loss: torch.Tensor,
    inputs: Sequence[torch.Tensor] | None,
    max_norm: float,
) -> None:
    loss.backward(inputs=inputs)
    if max_norm > 0:
        params = inputs or [p for group in optimizer.param_groups for p in group["params"]]
        # foreach where the device has it (the CPU and CUDA: one kernel), per tensor elsewhere
        nn.utils.clip_grad_norm_(params, max_norm, foreach=None)
    optimizer.step()


def joint_step(
    optimizers: Iterable[torch.optim.Optimizer],
    loss: torch.Tensor,
    clip: Iterable[Iterable[torch.Tensor]] = (),
    max_norm: float = 0.0,
) -> None:
    """One backward pass of a sum of losses that each reach only their own optimiser's
    parameters, then a step of every optimiser; ``max_norm`` > 0 clips each parameter group of
    ``clip`` to that global norm first (one norm per group, as Acme clips each network)."""
    optimizers = list(optimizers)
    for optimizer in optimizers:
        optimizer.zero_grad(set_to_none=True)
    loss.backward()
    if max_norm > 0:
        for params in clip:
            # foreach=None: the fused kernel where the device has one (not on meta)
            nn.utils.clip_grad_norm_(params, max_norm, foreach=None)
    for optimizer in optimizers:
        optimizer.step()


def slice_rows(agent: str, rows: Any) -> int:
    """A config's ``cpu_slice_rows`` checked: a whole number >= 0 (0: one pass over all rows)."""
    if isinstance(rows, bool) or not isinstance(rows, int | np.integer) or rows < 0:
        raise RluError(
            f"{agent} config cpu_slice_rows={rows!r}: use a whole number of rows >= 1, or 0 for "
            "one pass over all rows"
        )
    return int(rows)


def cpu_slices(device: torch.device, rows: int, total: int) -> int:
    """Rows per slice of a no-gradient pass over ``total`` rows: ``rows`` on a CPU (so that one
    slice's activations stay in the core's cache, docs/agents.md), all of them on other devices
    or when ``rows`` is 0."""
    return rows if device.type == "cpu" and rows else max(total, 1)


def frozen_copy(module: _Module) -> _Module:
    """A target network: a deep copy that takes no gradients."""
    return copy.deepcopy(module).requires_grad_(False)


class ActorCritic(NamedTuple):
    """What :func:`actor_critic` builds around an actor and a critic: their frozen targets, the
    modules of the agent's state and its two optimisers, and ``{target: source}``."""

    target_actor: nn.Module
    target_critic: nn.Module
    modules: dict[str, nn.Module]
    optimizers: dict[str, torch.optim.Optimizer]
    targets: dict[nn.Module, nn.Module]


def actor_critic(
    actor: nn.Module,
    critic: nn.Module,
    actor_lr: float,
    critic_lr: float,
    names: tuple[str, str] = ("policy", "critic"),
    more: Mapping[str, nn.Module] | None = None,
) -> ActorCritic:
    """Targets, state and optimisers of an actor-critic agent (D4PG, CRR, TD3+BC, ReBRAC): a
    frozen copy of each network; the modules ``{actor, critic, *more, target_actor,
    target_critic}`` under ``names`` (the targets as ``target_<name>``, in this order, which is
    the checkpoint's); one Adam per network, keyed ``names[0]`` and ``"critic"``."""
    target_actor, target_critic = frozen_copy(actor), frozen_copy(critic)
    a, c = names
    modules = {a: actor, c: critic, **(more or {}),
               f"target_{a}": target_actor, f"target_{c}": target_critic}  # fmt: skip
    optimizers: dict[str, torch.optim.Optimizer] = {
        a: adam(actor.parameters(), actor_lr),
        "critic": adam(critic.parameters(), critic_lr),
    }
    targets = {target_actor: actor, target_critic: critic}
    return ActorCritic(target_actor, target_critic, modules, optimizers, targets)


def hard_update(target: nn.Module, source: nn.Module) -> None:
    with torch.no_grad():
        torch._foreach_copy_(list(target.parameters()), list(source.parameters()))


def soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """Polyak averaging: target <- (1 - tau) target + tau source."""
    with torch.no_grad():
        torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)


def soft_updates(targets: Mapping[_Module, nn.Module], tau: float) -> None:
    """:func:`soft_update` of every ``{target: source}`` pair in one foreach call."""
    with torch.no_grad():
        torch._foreach_lerp_(
            [p for target in targets for p in target.parameters()],
            [p for source in targets.values() for p in source.parameters()],
            tau,
        )


def periodic_update(step: int, period: int, targets: Mapping[_Module, nn.Module]) -> None:
    """Hard-copy each source into its target every ``period`` steps (``{target: source}``)."""
    if period > 0 and step % period == 0:
        for target, source in targets.items():
            hard_update(target, source)


def advance(
    step: int,
    period: int = 0,
    targets: Mapping[_Module, nn.Module] | None = None,
    tau: float = 0.0,
) -> int:
    """The step count after one more update, once that update's target updates are made
    (``{target: source}``): a hard copy every ``period`` steps, or with ``period`` 0 Polyak
    averaging at rate ``tau`` every step (none if ``tau`` is 0 too)."""
    step += 1
    if period > 0:
        periodic_update(step, period, targets or {})
    elif tau > 0:
        soft_updates(targets or {}, tau)
    return step


def learn(
    optimizer: torch.optim.Optimizer,
    loss: torch.Tensor,
    step: int,
    period: int = 0,
    targets: Mapping[_Module, nn.Module] | None = None,
) -> int:
    """One gradient step, then :func:`advance`: returns the new step count."""
    sgd_step(optimizer, loss)
    return advance(step, period, targets)


def agent_state(
    modules: Mapping[str, nn.Module],
    optimizers: Mapping[str, torch.optim.Optimizer],
    generators: Mapping[str, torch.Generator],
    step: int,
) -> dict[str, Any]:
    """Everything an agent needs to resume (the checkpoint format in the module docstring), as
    a snapshot: copies, not the live tensors that ``nn.Module.state_dict`` and
    ``Optimizer.state_dict`` hand out, so the agent's later updates leave it as it was (RWRL
    keeps one per chunk in memory and loads the best one at the end)."""
    return {
        "modules": {k: _copied(m.state_dict()) for k, m in modules.items()},
        "optimizers": {k: copy.deepcopy(o.state_dict()) for k, o in optimizers.items()},
        "generators": {k: g.get_state() for k, g in generators.items()},
        "generator_devices": {k: g.device.type for k, g in generators.items()},
        "step": int(step),
    }


def _copied(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A module's ``state_dict`` with every tensor copied (the same dict type and metadata)."""
    for key, value in state.items():
        state[key] = value.clone()
    return state


def load_agent_state(
    state: Mapping[str, Any],
    modules: Mapping[str, nn.Module],
    optimizers: Mapping[str, torch.optim.Optimizer],
    generators: Mapping[str, torch.Generator],
) -> int:
    """Restore what :func:`agent_state` saved, onto the devices the agent lives on (modules and
    optimisers copy in; a checkpoint is read on the CPU); returns the step.

    A generator saved on another device type cannot go on: a CPU generator's state is a
    Mersenne Twister, a CUDA one's a Philox seed and offset. Such a generator restarts from a
    seed taken from the saved state (the same checkpoint gives the same stream); everything
    else resumes exactly. Checkpoints older than ``generator_devices`` were written on the CPU.
    """
    for k, m in modules.items():
        m.load_state_dict(state["modules"][k])
    for k, o in optimizers.items():
        # a copy: ``Optimizer.load_state_dict`` keeps the very tensors it is given (on the same
        # device and dtype), so two agents loaded from one in-memory state would step on each
        # other's Adam moments (and on the state's)
        o.load_state_dict(copy.deepcopy(state["optimizers"][k]))
    saved_on = state.get("generator_devices", {})
    for k, g in generators.items():
        saved = state["generators"][k]
        if saved_on.get(k, "cpu") == g.device.type:
            g.set_state(saved)
        else:
            digest = hashlib.sha256(saved.cpu().numpy().tobytes()).digest()
            g.manual_seed(int.from_bytes(digest[:8], "little") >> 1)
    return int(state["step"])


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
