"""scripts/d4pg_critic_probe.py on a short real D4PG run: its figures, and a clear error for a
run of another agent or data with other observations."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "d4pg_critic_probe.py"
ENV = "tests.train.pendulum:make_env"


def probe(*args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(SCRIPT), *args]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)


def short_run(tmp_path: Path, agent: str, data: Path) -> Path:
    from rlu.train import TrainConfig, train

    cfg = TrainConfig(task="test/pendulum", agent=agent, dataset=str(data), steps=3,
                      eval_every=-1, checkpoint_every=3, env=ENV)  # fmt: skip
    train(cfg, tmp_path / agent.split(".")[-1], progress=False)
    return tmp_path / agent.split(".")[-1]


def test_discounted_returns_match_the_closed_form():
    spec = importlib.util.spec_from_file_location("d4pg_critic_probe", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    g, n = 0.99, 50
    expected = (1 - g ** (n - np.arange(n))) / (1 - g)  # reward 1 on every one of n steps
    np.testing.assert_allclose(mod.discounted_returns(np.ones(n), g), expected, rtol=1e-12)


def test_probe_reads_a_d4pg_run_and_refuses_other_runs_and_data(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("gymnasium")
    from tests.train.pendulum import write_dataset

    data = write_dataset(tmp_path / "data", "test/pendulum", episodes=4)
    run = short_run(tmp_path, "d4pg", data)
    out = probe(str(run), str(data), "--episodes", "3")
    assert out.returncode == 0, out.stderr[-2000:]
    values = {
        name: float(re.search(rf"{re.escape(name)}:\s+(-?[\d.]+)", out.stdout).group(1))
        for name in ("Q(s, data action)", "Q(s, policy action)", "Q(s, random action)")
    }
    # the small preset's critic: 51 atoms on [-100, 100], so every expected value lies inside
    assert all(-100 <= v <= 100 for v in values.values()), out.stdout
    assert "data: 4 episodes" in out.stdout

    other = short_run(tmp_path, "tests.train.fake_agent", data)
    bad = probe(str(other), str(data))
    assert bad.returncode != 0 and "Traceback" not in bad.stderr
    assert "this probe reads the categorical critic of a 'd4pg' run" in bad.stderr

    foreign = write_dataset(tmp_path / "heavy", "test/pendulum_heavy", episodes=2)
    same_keys = probe(str(run), str(foreign), "--episodes", "1")
    assert same_keys.returncode == 0, same_keys.stderr[-2000:]  # same observation spec: allowed

    cartpole = ROOT / "rlu" / "resources" / "datasets" / "control_suite" / "cartpole_swingup"
    mismatch = probe(str(run), str(cartpole))
    assert mismatch.returncode != 0 and "Traceback" not in mismatch.stderr
    assert "observations are not those" in mismatch.stderr

    missing = probe(str(run), str(tmp_path / "nowhere"))
    assert missing.returncode != 0 and "Traceback" not in missing.stderr
    assert "nowhere" in missing.stderr
