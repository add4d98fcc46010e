"""Policy factories for ``rlu generate --policy`` tests: factory(task_id, seed) -> policy."""

from __future__ import annotations

import numpy as np

BUILT: list[tuple[str, int]] = []


def uniform(task_id: str, seed: int):
    from rlu.tasks import get_task

    BUILT.append((task_id, seed))
    shape = get_task(task_id).action_spec.shape
    rng = np.random.default_rng(seed)
    return lambda obs: rng.uniform(-1.0, 1.0, shape).astype(np.float32)
