"""``bench/gpu.py`` runs on the CPU, so the script a GPU session runs in its few device minutes
is known to work before it gets there: every figure is measured (no rate is judged here: the
bench prints them), every device check passes, the streamed DQN and Decision Transformer
figures are there."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow  # ~10-30 s on a 2-core machine: data, two agents, the loop, the checks
def test_the_gpu_bench_runs_every_figure_and_check_on_the_cpu(tmp_path):
    pytest.importorskip("torch")
    out = tmp_path / "gpu.json"
    argv = [sys.executable, str(ROOT / "bench" / "gpu.py"), "--device", "cpu", "--agents",
            "bc,dqn", "--stream-agents", "dqn,dt", "--seconds", "0.2", "--atari-steps", "600",
            "--control-steps", "600", "--json", str(out)]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=900)  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    report = json.loads(out.read_text())
    assert report["device"] == "cpu"
    for agent in ("bc", "dqn"):
        figures = report["agents"][agent]
        for name in ("alone fp32", "loop prefetch", "loop on-device"):
            assert math.isfinite(figures[name]) and figures[name] > 0, (agent, name, figures)
    for agent, kind in (("dqn", "transition"), ("dt", "sequence")):
        fig = report["stream"][agent]
        assert fig["kind"] == kind and fig["streamed"] > 0 and fig["alone"] > 0, fig
    checks = report["checks"]
    assert len(checks) >= 6 and all(c["ok"] is not False for c in checks), checks
