"""scripts/d4pg_critic_probe.py on a short real D4PG run: its figures, and a clear error for a
run of another agent or data with other observations."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.scripts import load_script

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "d4pg_critic_probe.py"
ENV = "tests.train.pendulum:make_env"


def probe(*args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(SCRIPT), *args]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)


def short_run(tmp_path: Path, agent: str, data: Path) -> Path:
    from rlu.training.train import train
    from tests.fakes import train_config

    cfg = train_config(task="test/pendulum", agent=agent, dataset=str(data), steps=3,
                      eval_every=-1, checkpoint_every=3, env=ENV)  # fmt: skip
    train(cfg, tmp_path / agent.split(".")[-1], progress=False)
    return tmp_path / agent.split(".")[-1]


def test_discounted_returns_match_the_closed_form():
    mod = load_script("d4pg_critic_probe")
    g, n = 0.99, 50
    expected = (1 - g ** (n - np.arange(n))) / (1 - g)  # reward 1 on every one of n steps
    np.testing.assert_allclose(mod.discounted_returns(np.ones(n), g), expected, rtol=1e-12)


def test_probe_reads_a_d4pg_run_and_refuses_other_runs_and_data(tmp_path):
    torch = pytest.importorskip("torch")
    pytest.importorskip("gymnasium")
    from tests.train.pendulum import write_dataset

    data = write_dataset(tmp_path / "data", "test/pendulum", episodes=4)
    run = short_run(tmp_path, "d4pg", data)
    out = probe(str(run), str(data), "--episodes", "3")
    assert out.returncode == 0, out.stderr[-2000:]
    assert re.search(r"Q\(s, random action\):\s+-?[\d.]+", out.stdout), out.stdout

    # A critic whose logits put all mass on atom 40 values every action at exactly that atom; over
    # all 4 episodes the discounted returns are those of every episode's steps 0, 10, 20, ...
    from rlu.data import open_dataset
    from rlu.training.restore import load_agent

    agent, _ = load_agent(run)
    head = agent.critic.head
    with torch.no_grad():
        head.linear.weight.zero_()
        head.linear.bias.fill_(-50.0)
        head.linear.bias[40] = 50.0
    ds = open_dataset(str(data))
    r = load_script("d4pg_critic_probe").measure(agent, ds, episodes=10)
    for name in ("data", "policy", "random"):
        np.testing.assert_allclose(r[name], float(head.atoms[40]), rtol=1e-5)
    g = agent.config.gamma
    expected = []
    for seg in ds.segments():
        n = len(seg.reward)
        per_step = [sum(seg.reward[t:] * g ** np.arange(n - t)) for t in range(0, n, 10)]
        expected.extend(per_step)
    assert len(r["mc"]) == len(expected)
    np.testing.assert_allclose(r["mc"].mean(), np.mean(expected), rtol=1e-6)
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
