"""Spec helpers the domain modules share (no domain's own data)."""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING

from rlu.types import ArraySpec, BoundedSpec

if TYPE_CHECKING:  # pragma: no cover
    from rlu.domains.spec import TaskRef, TaskSpec


def f32(*shape: int) -> ArraySpec:
    """A float32 array spec of ``shape``."""
    return ArraySpec(tuple(shape), "float32")


def obs(**dims: int) -> Mapping[str, ArraySpec]:
    """A dict observation spec of float32 vectors, keys in the order given."""
    return MappingProxyType({k: f32(d) for k, d in dims.items()})


def act(n: int) -> BoundedSpec:
    """A continuous action in [-1, 1]^n."""
    return BoundedSpec((n,), "float32", -1.0, 1.0)


CAMERA = ArraySpec((64, 64, 3), "uint8")


def config_task_ref(
    domain: str,
    tasks: Mapping[str, TaskSpec],
    name: str,
    builder: str,
    config: str,
    family: str,
    fix: str,
) -> TaskRef:
    """A TFDS name whose config is a task's name (``rlu_control_suite/cartpole_swingup``): that
    task of ``domain``; a domain's ``tfds_ref`` is ``functools.partial(config_task_ref, NAME)``."""
    from rlu.domains.spec import TaskRef
    from rlu.types import RluError

    task = tasks.get(f"{domain}/{config}")
    if task is None:
        raise RluError(f"{name!r}: {builder} has no config {config!r}; {fix}")
    return TaskRef(task, name, family=family)
