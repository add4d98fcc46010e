"""FQE on a device: everything up to the estimate's one host copy runs on the device it is given
(checked on meta, PyTorch's shape-only device), and the CPU gives the default's number."""

from __future__ import annotations

import numpy as np
import pytest

from rlu.evaluation.fqe import FQEConfig, fqe_estimate
from rlu.types import BoundedSpec, DiscreteSpec, Transition

torch = pytest.importorskip("torch")
CFG = FQEConfig(steps=5, batch_size=8, target_period=2)


def _data(discrete: bool):
    rng = np.random.default_rng(0)
    n = 40

    def action():
        if discrete:
            return rng.integers(0, 3, n).astype(np.int64)
        return rng.uniform(-1, 1, (n, 2)).astype(np.float32)

    obs = {"a": rng.standard_normal((n, 3)).astype(np.float32), "b": rng.random((n, 1))}
    nxt = {"a": rng.standard_normal((n, 3)).astype(np.float32), "b": rng.random((n, 1))}
    tr = Transition(obs, action(), rng.random(n).astype(np.float32), np.ones(n, np.float32),
                    nxt, action())  # fmt: skip
    spec = DiscreteSpec((), "int64", 3) if discrete else BoundedSpec((2,), "float32")

    def policy(o, first, reward):
        rows = len(o["a"])
        return np.ones(rows, np.int64) if discrete else np.zeros((rows, 2), np.float32)

    return tr, {k: v[:4] for k, v in obs.items()}, policy, spec


@pytest.mark.parametrize("discrete", [False, True])
def test_fqe_runs_on_its_device_up_to_the_estimate(discrete):
    tr, init, policy, spec = _data(discrete)
    with pytest.raises(RuntimeError, match="item\\(\\) cannot be called on meta"):
        fqe_estimate(tr, init, policy, spec, CFG, device=torch.device("meta"))
    default = fqe_estimate(tr, init, policy, spec, CFG)
    assert np.isfinite(default)
    assert fqe_estimate(tr, init, policy, spec, CFG, device="cpu") == default
