"""scripts/fidelity_study.sh end to end at the tiny scale: data, both sweeps, the report with the
paper's numbers beside, and a second run that only redraws the report (every step resumes)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_the_study_script_runs_end_to_end_and_resumes(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    pytest.importorskip("jinja2")
    env = {
        **os.environ,
        "OUT": str(tmp_path / "study"),
        "TASKS": "cartpole_swingup",
        "SEEDS": "0",
        "SCALE": "tiny",
        "STEPS": "30",
        "EVAL_EPISODES": "1",
        "WORKERS": "1",
        "RLU": f"{sys.executable} -m rlu",
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
    }
    script = ["bash", str(ROOT / "scripts" / "fidelity_study.sh")]
    first = subprocess.run(script, env=env, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert first.returncode == 0, first.stderr[-3000:]
    study = tmp_path / "study"
    assert (study / "data" / "cartpole_swingup" / "manifest.json").exists()
    assert (study / "curves" / "cartpole_swingup.png").stat().st_size > 0
    report = json.loads((study / "report" / "report.json").read_text())
    row = report["domains"]["control_suite"]["online"]["rows"][0]
    assert sorted(row["cells"]) == ["bc", "bcq", "brac", "d4pg", "rabm"]  # the paper's five
    assert sorted(row["paper"]) == sorted(row["cells"])  # its table beside ours
    md = (study / "report" / "report.md").read_text()
    assert "386.0 ± 6.0" in md  # the paper's BC on cartpole swingup
    # a small-preset, laptop-data study: the report says so and heads the paper as not comparable
    assert "| bc: paper (" in md and "): not comparable to these cells |" in md
    assert "preset small, 30 learner steps" in md and "No run here meets them" in md
    stamps = {p: p.stat().st_mtime_ns for p in study.rglob("result.json")}
    again = subprocess.run(script, env=env, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert again.returncode == 0, again.stderr[-3000:]
    assert {p: p.stat().st_mtime_ns for p in study.rglob("result.json")} == stamps  # nothing rerun
