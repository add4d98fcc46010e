"""torch state files (training checkpoints, generation state): saved atomically, loaded as input
that may be damaged or hostile.

A state file (``rlu train``'s ``checkpoints/step_*.pt``, ``rlu generate``'s resume state) holds
tensors, numbers, strings and plain containers only. It is written through ``rlu.files``
(temporary file created without following links, synced, renamed) and loaded with
``torch.load(weights_only=True)``: torch's restricted
unpickler, which refuses any other Python object instead of running the code a pickle can carry.
Its refusal message suggests ``weights_only=False``, which would run that code; rlu never passes
that advice on. An empty, truncated or foreign file, or one holding Python objects, raises a
:class:`~rlu.types.FormatError` naming the file and the fix. torch is imported on first use.

The bytes of a state file are a function of its values: pickle writes a second reference to one
Python object as a back-reference, so the same state pickled from objects shared differently
gave other bytes (a resumed run's optimiser state holds the key ``'step'`` as a string read from
its checkpoint, an uninterrupted run's the very string of the top-level key, and its checkpoints
differed byte for byte from the uninterrupted run's). :func:`save_state` saves a copy of the
containers with every string interned and no container shared (:func:`canonical`).
"""

from __future__ import annotations

import os
import sys
from collections import OrderedDict
from pathlib import Path
from typing import Any

from rlu.files import atomic_path
from rlu.types import FormatError, RluError

CHECKPOINT_FIX = "use a checkpoint written by rlu train, or an earlier one of the run (or re-train)"


def save_state(path: str | os.PathLike, state: Any) -> Path:
    """``torch.save(state)`` to ``path`` atomically (nothing partial is left by a kill or a full
    disk: the temporary file is removed)."""
    import torch

    state = canonical(state)
    with atomic_path(path) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC)
        with os.fdopen(fd, "wb") as fh:
            torch.save(state, fh)
    return Path(path)


def canonical(state: Any) -> Any:
    """``state`` with its dicts, lists and tuples copied and its strings interned: equal strings
    are one object and no container is reached twice, so its pickle depends on the values only.
    An ``OrderedDict`` stays one, with its attributes (a module state dict's ``_metadata``);
    tensors and other leaves are kept as they are (storages shared between tensors stay shared:
    torch writes a storage once by identity, as the state shares it)."""
    kind = type(state)
    if kind is str:
        return sys.intern(state)
    if kind is dict or kind is OrderedDict:
        out = kind((canonical(k), canonical(v)) for k, v in state.items())
        for name, value in vars(state).items() if kind is OrderedDict else ():
            setattr(out, name, canonical(value))
        return out
    if kind is list or kind is tuple:
        return kind(canonical(v) for v in state)
    return state


def load_state(
    path: str | os.PathLike, keys: tuple[str, ...] = (), fix: str = CHECKPOINT_FIX
) -> dict[str, Any]:
    """The state dict saved at ``path``, which must hold ``keys`` at its top level."""
    import torch

    path = Path(path)
    if not path.is_file():
        raise RluError(f"{path}: no such state file; {fix}")
    if path.stat().st_size == 0:
        raise FormatError(f"{path}: an empty file (0 bytes), not a state file; {fix}")
    try:
        # on the CPU whatever device wrote it: a GPU run's checkpoint loads on a CPU-only machine
        state = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as e:  # noqa: BLE001 (torch raises UnpicklingError, RuntimeError, EOFError...)
        # torch's own text is not repeated: for a refused object it recommends unsafe loading
        text = str(e).lower().replace("_", " ")
        # "Unsupported operand": bytes that are no pickle at all, not a refused object
        refused = "weights only" in text and "unsupported operand" not in text
        if type(e).__name__ == "UnpicklingError" and refused:
            why = (
                "it holds Python objects besides tensors and plain containers; rlu does not load "
                "them (unpickling them would run code stored in the file)"
            )
        else:
            why = f"it is truncated or not a torch checkpoint ({type(e).__name__})"
        raise FormatError(f"{path}: {why}; {fix}") from None
    if not isinstance(state, dict):
        raise FormatError(f"{path}: holds a {type(state).__name__}, not a state dict; {fix}")
    missing = [k for k in keys if k not in state]
    if missing:
        raise FormatError(f"{path}: no {missing} entries; {fix}")
    return state
