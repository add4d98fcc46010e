"""D4PG starts from Acme's initialisation (acme/tf/networks/continuous.py, distributional.py):
the weights' statistics against Keras' VarianceScaling and Sonnet's default formulas, within
sampling tolerance (4 standard errors of a std estimated from n draws), and rlu's earlier init
as ``init="torch"`` keeps for the bundled data's behaviour agents."""

from __future__ import annotations

import math

import pytest

torch = pytest.importorskip("torch")

from rlu.agents import make_agent  # noqa: E402
from rlu.types import BoundedSpec, RluError  # noqa: E402
from tests.fakes import LOWDIM_OBS  # noqa: E402

ACTION = BoundedSpec((6,), "float32", -1.0, 1.0)  # 6 x 256 = 1,536 draws in the last layer
TRUNC = 0.87962566103423978  # std of a unit normal truncated to +-2


def _linears(module):
    return [m for m in module.modules() if isinstance(m, torch.nn.Linear)]


def _std_close(w, expected, kurtosis):
    """The draws' std within 4 standard errors of ``expected`` (SE of a std from n draws of a
    distribution of that kurtosis: sqrt((kurtosis - 1) / n) / 2, relative)."""
    n = w.numel()
    tol = 4 * 0.5 * math.sqrt((kurtosis - 1) / n)
    got = float(w.double().pow(2).mean().sqrt())  # mean 0 by construction
    assert abs(got / expected - 1) < tol, (tuple(w.shape), got, expected, tol)


# kurtosis of U(-a, a): 1.8; of N(0, 1) truncated to +-2: 2.37
UNIFORM_K, TRUNC_K = 1.8, 2.37


def test_d4pg_weights_start_as_acmes():
    agent = make_agent("d4pg", LOWDIM_OBS, ACTION, preset="paper", seed=3)
    for mlp in (agent.policy.mlp, agent.critic.mlp):
        layers = _linears(mlp)
        assert len(layers) == 3
        for layer in layers:  # VarianceScaling(0.333, fan_out, uniform), zero bias
            fan_out = layer.out_features
            limit = math.sqrt(3 * 0.333 / fan_out)
            w = layer.weight.detach()
            assert float(w.abs().max()) <= limit and float(w.abs().max()) > 0.99 * limit
            _std_close(w, math.sqrt(0.333 / fan_out), UNIFORM_K)
            assert not layer.bias.detach().any()
        ln = next(m for m in mlp.modules() if isinstance(m, torch.nn.LayerNorm))
        assert bool((ln.weight == 1).all()) and not ln.bias.detach().any()
    out = agent.policy.out  # NearZeroInitializedLinear: VarianceScaling(1e-4), fan_in, trunc.
    w, std = out.weight.detach(), math.sqrt(1e-4 / out.in_features)
    assert float(w.abs().max()) <= 2 * std / TRUNC
    _std_close(w, std, TRUNC_K)
    assert not out.bias.detach().any()
    head = agent.critic.head.linear  # snt.Linear's default: truncated normal, 1 / sqrt(fan_in)
    w, pre = head.weight.detach(), 1 / math.sqrt(head.in_features)
    assert float(w.abs().max()) <= 2 * pre
    _std_close(w, pre * TRUNC, TRUNC_K)
    assert not head.bias.detach().any()


def test_d4pg_torch_init_is_rlus_earlier_one():
    agent = make_agent("d4pg", LOWDIM_OBS, ACTION, preset="paper", seed=3, init="torch")
    out = agent.policy.out  # torch's U(+-1/sqrt(fan_in)) times 1e-4: ~170x below Acme's
    _std_close(out.weight.detach(), 1e-4 / math.sqrt(3 * out.in_features), UNIFORM_K)
    first = agent.policy.mlp[0]  # torch's default: bias U(+-1/sqrt(fan_in)), not 0
    assert first.bias.detach().abs().max() > 0
    _std_close(first.weight.detach(), 1 / math.sqrt(3 * first.in_features), UNIFORM_K)
    with pytest.raises(RluError, match="init"):
        make_agent("d4pg", LOWDIM_OBS, ACTION, preset="small", init="keras")
