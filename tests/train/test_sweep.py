"""Sweeps: 2 tasks x 2 agents x 2 configurations x 2 seeds on the local pool and on a local Ray
instance give the same results table; completed runs are skipped on a second run."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from rlu.training.runs import load_results
from rlu.training.sweep import SweepConfig, expand, results_table, sweep
from rlu.types import RluError
from rlu.workers import Backend
from tests.train.conftest import AGENTS
from tests.train.conftest import sweep_config as _config


def test_expand_uses_each_agents_grid(pendulum_datasets, tmp_path):
    runs = expand(_config(pendulum_datasets), tmp_path)
    assert len(runs) == 2 * 2 * 2 * 2
    assert {r.config for r in runs} == {"learning_rate=0.01", "learning_rate=0.003"}
    assert len({r.run_dir for r in runs}) == 16
    with pytest.raises(RluError, match="--dataset"):
        expand(SweepConfig(tasks=("x",), agents=AGENTS, datasets={}), tmp_path)


def test_local_sweep_then_skip_completed(local_sweep, pendulum_datasets):
    out, records = local_sweep
    assert len(records) == 16
    assert all(isinstance(r["score"], float) for r in records)
    assert load_results(out) == records
    # a record's score is its run's last evaluation
    for r in records:
        evals = (Path(r["run"]) / "eval.jsonl").read_text().splitlines()
        assert json.loads(evals[-1])["mean"] == r["score"]
    # running it again trains nothing: every run folder is left as it was
    stamps = {r["run"]: (Path(r["run"]) / "result.json").stat().st_mtime_ns for r in records}
    again = sweep(_config(pendulum_datasets), out, Backend("local", 1))
    assert again == records
    assert stamps == {
        r["run"]: (Path(r["run"]) / "result.json").stat().st_mtime_ns for r in records
    }


def test_ray_sweep_gives_the_same_table(local_sweep, pendulum_datasets, tmp_path):
    pytest.importorskip("ray")
    _, local_records = local_sweep
    records = sweep(_config(pendulum_datasets), tmp_path / "ray", Backend("ray"))
    assert results_table(records) == results_table(local_records)
    assert [r["returns"] for r in records] == [r["returns"] for r in local_records]


def test_sweep_refuses_a_different_config_in_the_same_folder(local_sweep, pendulum_datasets):
    out, _ = local_sweep
    cfg = _config(pendulum_datasets)
    other = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, steps=31))
    with pytest.raises(RluError, match="different sweep configuration"):
        sweep(other, out)


def test_cli_sweep_and_report(pendulum_datasets, tmp_path):
    pytest.importorskip("matplotlib")
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    out = tmp_path / "sweep"
    args = [
        sys.executable, "-m", "rlu", "sweep", "--tasks", "test/pendulum",
        "--agents", "tests.train.fake_agent", "--grid", "learning_rate=0.01,0.02",
        "--dataset", f"test/pendulum={pendulum_datasets['test/pendulum']}",
        "--seeds", "0", "--steps", "5", "--eval-episodes", "1", "--eval-max-steps", "5",
        "--env", "tests.train.pendulum:make_env", "--workers", "1", "--out", str(out),
    ]  # fmt: skip
    res = subprocess.run(args, cwd=root, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "learning_rate=0.02" in res.stdout and "learning_rate=0.01" in res.stdout
    records = load_results(out)
    assert [r["overrides"] for r in records] == [{"learning_rate": 0.01}, {"learning_rate": 0.02}]
    cfg = json.loads((Path(records[1]["run"]) / "config.json").read_text())
    assert cfg["agent_config"]["learning_rate"] == 0.02
    assert cfg["train"]["run"]["eval_every"] is None  # the default: 5 steps evaluate at the end
    assert len((Path(records[1]["run"]) / "eval.jsonl").read_text().splitlines()) == 1
    res = subprocess.run(
        [sys.executable, "-m", "rlu", "report", str(out)], cwd=root, capture_output=True, text=True
    )
    assert res.returncode == 0, res.stderr
    assert (out / "report" / "report.html").exists()
    assert (out / "report" / "figures" / "other_tasks.png").exists()


def test_an_interrupted_sweep_keeps_the_results_of_its_finished_runs(
    local_sweep, pendulum_datasets, tmp_path, monkeypatch
):
    import shutil

    import rlu.training.sweep as sweep_module

    out, records = local_sweep
    shutil.copytree(out, tmp_path / "again")
    (tmp_path / "again" / "results.jsonl").unlink()
    real, done = sweep_module.run_one, []

    def interrupted_after_three(spec, config):
        if len(done) == 3:
            raise KeyboardInterrupt  # Ctrl-C during the fourth run
        done.append((spec.task, spec.agent, spec.config, spec.seed))
        return real(spec, config)

    monkeypatch.setattr(sweep_module, "run_one", interrupted_after_three)
    with pytest.raises(KeyboardInterrupt):
        sweep(_config(pendulum_datasets), tmp_path / "again", Backend("local", 1))
    kept = load_results(tmp_path / "again")  # what rlu report reads
    assert [(r["task"], r["agent"], r["config"], r["seed"]) for r in kept] == sorted(done)
    by_key = {(r["task"], r["agent"], r["config"], r["seed"]): r["score"] for r in records}
    assert [r["score"] for r in kept] == [by_key[k] for k in sorted(done)]


def test_a_failing_run_leaves_the_others_running_and_is_named_at_the_end(
    local_sweep, pendulum_datasets, tmp_path
):
    import shutil

    from rlu.locks import OutputLock

    out, records = local_sweep
    again = tmp_path / "again"
    shutil.copytree(out, again)
    (again / "results.jsonl").unlink()
    spec = expand(_config(pendulum_datasets), again)[5]
    (Path(spec.run_dir) / "result.json").unlink()  # this run must train again...
    with OutputLock(spec.run_dir, "run folder"):  # ...but another process holds its folder
        with pytest.raises(RluError, match=r"1 of 16 runs failed") as err:
            sweep(_config(pendulum_datasets), again, Backend("local", 2))
    assert f"{spec.run_dir}: LockBusy" in str(err.value) and "run the sweep again" in str(err.value)
    kept = load_results(again)  # the 15 others finished and were recorded
    assert len(kept) == 15 and spec.run_dir not in {r["run"] for r in kept}


def test_a_sweep_made_with_relative_paths_reports_from_anywhere(pendulum_datasets, tmp_path):
    """sweep.json keeps its datasets resolved and results.jsonl its runs relative to the sweep
    folder, so the sweep reports (and moves) independent of the folder it was started in."""
    pytest.importorskip("matplotlib")
    import os
    import shutil
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    work = tmp_path / "work"
    shutil.copytree(Path(pendulum_datasets["test/pendulum"]), work / "data")
    env = {**os.environ, "PYTHONPATH": str(root)}
    args = [sys.executable, "-m", "rlu", "sweep", "--tasks", "test/pendulum",
            "--agents", "tests.train.fake_agent", "--grid", "learning_rate=0.01",
            "--dataset", "test/pendulum=data", "--steps", "3", "--eval-episodes", "1",
            "--eval-max-steps", "5", "--env", "tests.train.pendulum:make_env", "--workers", "1",
            "--out", "sweep"]  # fmt: skip
    res = subprocess.run(args, cwd=work, env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    saved = json.loads((work / "sweep" / "sweep.json").read_text())
    assert saved["datasets"] == {"test/pendulum": str((work / "data").resolve())}
    line = json.loads((work / "sweep" / "results.jsonl").read_text().splitlines()[0])
    assert not Path(line["run"]).is_absolute()
    shutil.move(work / "sweep", tmp_path / "moved")  # the sweep folder moved elsewhere
    res = subprocess.run([sys.executable, "-m", "rlu", "report", str(tmp_path / "moved")],
                         cwd=root, env=env, capture_output=True, text=True)  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert load_results(tmp_path / "moved")[0]["run"].startswith(str(tmp_path / "moved"))


def test_cli_sweep_takes_config_and_log_to_like_train(pendulum_datasets, tmp_path, capsys):
    """``rlu sweep --config`` reads a sweep config (YAML here), a sweep folder's sweep.json, or
    a run config (``rlu train --config``'s: a sweep of its one run); options typed beside it
    win. ``--log-to csv`` writes each run's metrics.csv and eval.csv, and a sweep is continued
    with other loggers (they change nothing the runs compute)."""
    pytest.importorskip("yaml")
    from rlu.cli import main

    data = pendulum_datasets["test/pendulum"]
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(
        "tasks: [test/pendulum]\n"
        "agents: [tests.train.fake_agent]\n"
        f"datasets: {{test/pendulum: {data}}}\n"
        "seeds: [0, 1]\n"
        "grid: {learning_rate: [0.01]}\n"
        "run: {steps: 4, eval_episodes: 1, eval_max_steps: 5, log_every: 2}\n"
    )
    common = ["--env", "tests.train.pendulum:make_env", "--workers", "1"]
    out = tmp_path / "s"
    # the agent module is named in the file: typed too, as rlu train asks
    argv = ["sweep", "--config", str(cfg), "--out", str(out), "--seeds", "3", *common]
    assert main(argv) == 2
    assert "never imported; if you trust it, type it: --agents" in capsys.readouterr().err
    assert not out.exists()
    assert main([*argv, "--agents", "tests.train.fake_agent", "--log-to", "csv"]) == 0
    records = load_results(out)
    assert [(r["seed"], r["config"], r["steps"]) for r in records] == [
        (3, "learning_rate=0.01", 4)  # --seeds typed: 3, not the file's 0 and 1
    ]
    run = Path(records[0]["run"])
    assert (run / "metrics.csv").is_file() and (run / "eval.csv").is_file()
    saved = json.loads((out / "sweep.json").read_text())
    assert saved["loggers"] == ["csv"] and saved["run"]["steps"] == 4
    # the sweep folder's own sweep.json as --config continues it, here with no logger
    again = ["sweep", "--config", str(out / "sweep.json"), "--out", str(out),
             "--agents", "tests.train.fake_agent", *common]  # fmt: skip
    assert main(again) == 0 and load_results(out) == records
    # a run's config.json: a sweep of that one run, its overrides a grid of one value each
    one = tmp_path / "one"
    argv = ["sweep", "--config", str(run / "config.json"), "--out", str(one),
            "--agents", "tests.train.fake_agent", *common]  # fmt: skip
    assert main(argv) == 0
    (rec,) = load_results(one)
    assert (rec["task"], rec["seed"], rec["overrides"]) == ("test/pendulum", 3, {
        "learning_rate": 0.01})  # fmt: skip
    assert rec["score"] == records[0]["score"]  # the same run, trained again: the same number


def test_cli_sweep_says_what_is_missing(tmp_path, capsys):
    from rlu.cli import main

    assert main(["sweep", "--out", str(tmp_path / "s")]) == 2
    assert "--tasks is missing: give it on the command line or in --config" in (
        capsys.readouterr().err
    )
    # no --dataset: each task's own dataset, as rlu.load_dataset names it (none for "t")
    assert main(["sweep", "--tasks", "t", "--agents", "bc", "--out", str(tmp_path / "s")]) == 2
    assert "t" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()
