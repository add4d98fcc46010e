"""How a run computes, apart from what it computes: the device, the numeric precision, TF32,
``torch.compile``, the data path (prefetch, the dataset held on the device) and the GPUs a Ray
run asks for. docs/devices.md explains the choices and what is bit-reproducible where.

A run's ``Runtime`` may change between its sessions (train on a GPU, resume or evaluate on a
CPU): ``rlu train --resume`` compares the run's config without it. Device strings are parsed
and checked in one place, ``resolve_device`` below. This module imports numpy only; torch
is imported when a runtime is resolved or applied.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from rlu.files import Checked
from rlu.types import RluError

DEVICES = "auto, cpu, cuda or cuda:N"
"""The device strings rlu accepts (``--device`` of the commands, ``device=`` of agents)."""


def resolve_device(device: Any = "auto") -> Any:
    """The ``torch.device`` that ``device`` names on this machine, checked here once for every
    part of rlu (agents, the loop, FQE, generation): ``auto`` is the first CUDA GPU if PyTorch
    sees one and the CPU otherwise; ``cuda`` is ``cuda:0``; ``cuda:N`` must exist. A
    ``torch.device`` passes through as given (the placement tests build agents on ``meta``).
    Imports torch."""
    import torch

    if isinstance(device, torch.device):
        return device
    text = device.strip().lower() if isinstance(device, str) else None
    if text == "cpu" or (text == "auto" and not torch.cuda.is_available()):
        return torch.device("cpu")
    if text == "auto":
        return torch.device("cuda", 0)
    kind, sep, index = (text or "").partition(":")
    if kind != "cuda" or (sep and not index.isdigit()):
        raise RluError(f"device {device!r}; use one of {DEVICES} (e.g. --device cuda:0)")
    if not torch.cuda.is_available():
        build = f"CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
        raise RluError(
            f"device {device!r}: PyTorch sees no CUDA GPU here (torch {torch.__version__}, "
            f"{build}); use --device cpu (or auto), or install a CUDA build of torch on a "
            "machine with an NVIDIA GPU"
        )
    count, number = torch.cuda.device_count(), int(index) if sep else 0
    if number >= count:
        visible = os.environ.get("CUDA_VISIBLE_DEVICES")
        seen = f" (CUDA_VISIBLE_DEVICES={visible})" if visible is not None else ""
        raise RluError(
            f"device {device!r}: PyTorch sees {count} CUDA GPU(s){seen}, cuda:0 .. "
            f"cuda:{count - 1}; pick one of those"
        )
    return torch.device("cuda", number)


PRECISIONS = ("fp32", "bf16")
DEFAULT_CUDA_PREFETCH = 2
"""Batches the loop samples ahead on CUDA when ``prefetch`` is None: one in the copy, one
waiting (a deeper queue only holds more pinned memory)."""


@dataclass(frozen=True)
class Runtime(Checked):
    """Where and how a run computes (``rlu.training.config.RunSettings.runtime``)."""

    device: str = field(default="cpu", metadata={"cli_default": "auto", "metavar": "DEVICE"})
    """auto, cpu, cuda or cuda:N: where the agent's modules, batches and random draws live
    (auto: the first CUDA GPU if PyTorch sees one, else the CPU; the command line's default,
    where the library's is cpu)."""
    precision: str = field(default="fp32", metadata={"choices": PRECISIONS})
    """fp32, or bf16: every update runs under ``torch.autocast`` with bfloat16 (matmuls and
    convolutions in bf16; weights, gradients and optimiser states stay fp32)."""
    tf32: bool = False
    """CUDA only: matmuls and cuDNN convolutions in TF32 (Ampere and newer). False keeps both
    IEEE fp32, so fp32 means fp32 (PyTorch's own default runs cuDNN convolutions in TF32)."""
    compile: bool = False
    """``torch.compile`` the forward of every agent module (opt-in: the first updates compile)."""
    prefetch: int | None = field(default=None, metadata={"min": 0, "max": 64, "metavar": "N"})
    """Batches sampled ahead of the learner by a background thread (on CUDA copied from pinned
    memory on a side stream); None: 2 on CUDA, 0 on the CPU (sampled in line, as before)."""
    data_on_device: bool = False
    """Hold the dataset's columns on the device and gather every batch there (transition
    batches; Atari frames stay uint8 and are stacked by index on the device)."""

    def __post_init__(self) -> None:
        if self.precision not in PRECISIONS:
            raise RluError(
                f"precision {self.precision!r}; use one of {', '.join(PRECISIONS)} "
                "(--precision bf16 trains under bfloat16 autocast)"
            )
        super().__post_init__()  # every field's type and bounds: prefetch an int in [0, 64]

    def resolve(self) -> Runtime:
        """This runtime on this machine: ``device`` as the canonical name of an existing
        device (``cuda:0``, ``cpu``), ``prefetch`` decided; options the device cannot honour
        are an error naming the fix. Imports torch."""
        import torch

        device = resolve_device(self.device)
        if self.tf32 and device.type != "cuda":
            raise RluError(
                f"--tf32 applies to CUDA GPUs (Ampere or newer); the run's device is {device}. "
                "Drop --tf32 (on a CPU, --precision bf16 is the reduced-precision option)"
            )
        if self.precision == "bf16" and device.type == "cuda":
            if not torch.cuda.is_bf16_supported():
                name = torch.cuda.get_device_name(device)
                raise RluError(
                    f"--precision bf16: {name} ({device}) has no bfloat16 support; use "
                    "--precision fp32 (with --tf32 on Ampere or newer)"
                )
        prefetch = self.prefetch
        if prefetch is None:
            prefetch = DEFAULT_CUDA_PREFETCH if device.type == "cuda" else 0
        return dataclasses.replace(self, device=str(device), prefetch=prefetch)

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @staticmethod
    def from_json(data: Mapping[str, Any] | None) -> Runtime:
        return Runtime(**dict(data or {}))


@contextlib.contextmanager
def numerics(runtime: Runtime) -> Iterator[Callable[[], Any]]:
    """Apply a resolved runtime's TF32 choice for the duration of a run (restored afterwards:
    the flags are process-wide) and yield the context each update runs in (bf16 autocast, or
    nothing)."""
    import torch

    device = torch.device(runtime.device)
    saved = None
    if device.type == "cuda":
        # the flags torch.compile's inductor reads too (mixing them with the newer
        # ``fp32_precision`` properties makes torch raise when either is read)
        saved = (torch.get_float32_matmul_precision(), torch.backends.cudnn.allow_tf32)
        torch.set_float32_matmul_precision("high" if runtime.tf32 else "highest")
        torch.backends.cudnn.allow_tf32 = runtime.tf32
    try:
        if runtime.precision == "bf16":
            # cache_enabled=False: autocast's cache keeps the bf16 copy of each parameter for the
            # whole context, and an update's optimiser steps change the parameters in place, so
            # with the cache every forward after a step (IQL's Q target from the V it just
            # stepped, BCQ's actor loss on its stepped critic and VAE, D4PG's and BRAC's policy
            # losses on the stepped critic) read the weights from before it. Recasting at each
            # use ran at 0.99-1.07x the cached speed (docs/devices.md).
            yield lambda: torch.autocast(device.type, dtype=torch.bfloat16, cache_enabled=False)
        else:
            yield contextlib.nullcontext
    finally:
        if saved is not None:
            torch.set_float32_matmul_precision(saved[0])
            torch.backends.cudnn.allow_tf32 = saved[1]


def compile_modules(modules: Mapping[str, Any]) -> list[str]:
    """``torch.compile`` every agent module in place (``nn.Module.compile``: the module, its
    parameters and its ``state_dict`` keys stay the same, so checkpoints do not change). A
    container without a forward (``ModuleDict``) has its children compiled instead; methods
    other than ``forward`` run eagerly. Returns the names of the compiled modules."""
    from torch import nn

    done: list[str] = []

    def visit(name: str, module: nn.Module) -> None:
        if type(module).forward is nn.Module.forward:  # a container: no forward of its own
            for child_name, child in module.named_children():
                visit(f"{name}.{child_name}", child)
            return
        module.compile()
        done.append(name)

    for name, module in modules.items():
        visit(name, module)
    return done


# --- Ray --------------------------------------------------------------------------------------
def check_gpus_per_run(gpus: float) -> float:
    """A Ray GPU request per run: 0 (none), a fraction in (0, 1] (several runs share one GPU:
    0.25 packs four) or a whole number of GPUs (Ray's rule for requests above one)."""
    value = float(gpus)
    if not value >= 0 or (value > 1 and not value.is_integer()):
        raise RluError(
            f"--gpus-per-run {gpus!r}; give 0, a fraction in (0, 1] (0.25: four runs share a "
            "GPU) or a whole number of GPUs"
        )
    return value


def ray_options(gpus_per_run: float) -> dict[str, float]:
    """The resources one run asks Ray for: a CPU, and ``gpus_per_run`` GPUs if any (Ray then
    sets the run's CUDA_VISIBLE_DEVICES to the GPU it was given, so ``auto`` and ``cuda`` find
    it as cuda:0)."""
    gpus = check_gpus_per_run(gpus_per_run)
    return {"num_cpus": 1, "num_gpus": gpus} if gpus else {"num_cpus": 1}


def check_ray_gpus(ray: Any, gpus_per_run: float, device: str) -> None:
    """Refuse, before submitting anything, runs Ray could never schedule (more GPUs per run
    than the cluster has: Ray would wait forever) or that ask for CUDA without a GPU (Ray hides
    every GPU from a task that requested none)."""
    gpus = check_gpus_per_run(gpus_per_run)
    have = float(ray.cluster_resources().get("GPU", 0.0))
    if gpus > have:
        raise RluError(
            f"--gpus-per-run {gpus:g}: the Ray cluster has {have:g} GPU(s), so no run could "
            "start; lower --gpus-per-run or add GPU nodes"
        )
    if gpus == 0 and device.strip().lower().startswith("cuda"):
        raise RluError(
            f"--device {device} on Ray needs --gpus-per-run (e.g. 0.25: four runs share a GPU): "
            "Ray gives GPUs only to runs that ask for them"
        )
