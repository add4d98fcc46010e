"""Loading a training checkpoint as input that may be damaged or hostile.

A checkpoint (``rlu train``'s ``checkpoints/step_*.pt``) holds tensors, numbers, strings and plain
containers only, and is loaded with ``torch.load(weights_only=True)``: torch's restricted
unpickler, which refuses any other Python object instead of running the code a pickle can carry.
Its refusal message suggests ``weights_only=False``, which would run that code; rlu never passes
that advice on. An empty, truncated or foreign file, or one holding Python objects, raises a
:class:`~rlu.types.FormatError` naming the file and the fix. torch is imported on first use.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from rlu.types import FormatError, RluError


def load_checkpoint(path: str | os.PathLike, keys: tuple[str, ...] = ()) -> dict[str, Any]:
    """The state dict saved at ``path``, which must hold ``keys`` at its top level."""
    import torch

    path = Path(path)
    fix = "use a checkpoint written by rlu train, or an earlier one of the run (or re-train)"
    if not path.is_file():
        raise RluError(f"{path}: no such checkpoint file; {fix}")
    if path.stat().st_size == 0:
        raise FormatError(f"{path}: an empty file (0 bytes), not a checkpoint; {fix}")
    try:
        state = torch.load(path, weights_only=True)
    except Exception as e:  # noqa: BLE001 (torch raises UnpicklingError, RuntimeError, EOFError...)
        # torch's own text is not repeated: for a refused object it recommends unsafe loading
        text = str(e).lower().replace("_", " ")
        if type(e).__name__ == "UnpicklingError" and "weights only" in text:
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
