"""scripts/precision_probe.py: its comparison, and bf16 against fp32 on one real IQL update of
the bundled cartpole data (the stale autocast weight cache put the critic's bf16 gradient 60 %
away from fp32's; the same arithmetic without it is about 1 % away)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

from tests.scripts import load_script

torch = pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "precision_probe.py"
DATA = ROOT / "rlu" / "resources" / "datasets" / "control_suite" / "cartpole_swingup"


def test_compare_is_the_relative_distance_and_the_cosine():
    mod = load_script("precision_probe")
    x = torch.tensor([3.0, 4.0], dtype=torch.float64)
    assert mod.compare(x, x) == pytest.approx((0.0, 1.0))
    assert mod.compare(x, 2 * x) == pytest.approx((1.0, 1.0))
    assert mod.compare(x, -x) == pytest.approx((2.0, -1.0))
    assert mod.compare(x, torch.tensor([-4.0, 3.0], dtype=torch.float64)) == pytest.approx(
        (math.sqrt(2), 0.0)
    )
    assert all(math.isnan(v) for v in mod.compare(torch.zeros(2), x))


def test_coherence_is_one_for_one_direction_and_small_for_unrelated_ones():
    mod = load_script("precision_probe")
    x = torch.tensor([3.0, 4.0, 0.0, 0.0], dtype=torch.float64)
    assert mod.coherence([x, 2 * x, 0.5 * x]) == pytest.approx(1.0)
    assert mod.coherence([x, -x]) == pytest.approx(0.0)
    basis = list(torch.eye(4, dtype=torch.float64))  # orthogonal, equal norms: 1 / sqrt(4)
    assert mod.coherence(basis) == pytest.approx(0.5)


def test_iql_bf16_gradients_are_close_to_fp32_and_under_the_batch_noise():
    from rlu.data import open_dataset

    mod = load_script("precision_probe")
    torch.set_num_threads(1)
    rows = mod.probe("iql", open_dataset(DATA), "small", [0], pairs=2, seed=0)
    assert {r["optimizer"] for r in rows} == {"value", "critic", "policy"}
    for r in rows:
        assert r["step"] == 0
        assert 0.0 < r["bf16_rel"] < 0.1 and r["bf16_cos"] > 0.99, r
        assert r["bf16_rel"] < r["batch_rel"], r
        assert 0.0 < r["bf16_coherence"] <= 1.0 and 0.0 < r["batch_coherence"] <= 1.0, r


@pytest.mark.parametrize(
    ("args", "message"),
    [(["iql", str(DATA), "--pairs", "0"], "--pairs must be 1 or more"),
     (["iql", str(DATA / "missing")], "missing"),
     (["no_such_agent", str(DATA)], "no_such_agent")],
)  # fmt: skip
def test_bad_arguments_are_one_clear_line(args, message):
    out = subprocess.run([sys.executable, str(SCRIPT), *args, "--at", "0"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert out.returncode != 0
    assert "Traceback" not in out.stderr, out.stderr[-2000:]
    assert message in out.stderr, out.stderr[-2000:]
