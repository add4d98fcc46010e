"""The loggers see what the run's own logs hold: CSV rows, TensorBoard scalars and the W&B run's
summary equal metrics.jsonl / eval.jsonl, and a resumed run's CSV is cut back to its checkpoint."""

from __future__ import annotations

import csv
import json

import pytest

from rlu.training.train import train
from rlu.types import RluError
from tests.fakes import train_config

ENV = "tests.train.pendulum:make_env"


def _config(dataset, **kw):
    base = dict(task="test/pendulum", agent="tests.train.fake_agent", dataset=dataset, steps=40,
                eval_every=20, eval_episodes=2, eval_envs=2, log_every=10, checkpoint_every=20,
                env=ENV)  # fmt: skip
    return train_config(**{**base, **kw})


def _jsonl(path):
    return [json.loads(x) for x in path.read_text().splitlines()]


def test_csv_rows_equal_the_json_logs(pendulum_datasets, tmp_path):
    run = tmp_path / "run"
    train(_config(pendulum_datasets["test/pendulum"]), run, loggers=("csv",))
    metrics = _jsonl(run / "metrics.jsonl")
    with open(run / "metrics.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["step"]) for r in rows] == [m["step"] for m in metrics]
    for row, m in zip(rows, metrics, strict=True):
        assert {k: float(v) for k, v in row.items()} == pytest.approx(m, rel=1e-12)
    evals = _jsonl(run / "eval.jsonl")
    with open(run / "eval.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(int(r["step"]), float(r["mean"])) for r in rows] == [
        (e["step"], e["mean"]) for e in evals
    ]


def test_a_resumed_runs_csv_is_cut_back_to_its_checkpoint(pendulum_datasets, tmp_path):
    data = pendulum_datasets["test/pendulum"]
    train(_config(data), tmp_path / "whole", loggers=("csv",))
    run = tmp_path / "cut"
    train(_config(data), run, loggers=("csv",))
    (run / "result.json").unlink()
    (run / "checkpoints" / "step_00000040.pt").unlink()  # resume from step 20
    with open(run / "metrics.csv", "a") as fh:
        fh.write("999,1,2\n")  # a row logged after the checkpoint, before a kill
    train(_config(data), run, resume=True, loggers=("csv",))
    assert (run / "metrics.csv").read_text() == (tmp_path / "whole" / "metrics.csv").read_text()


def test_tensorboard_scalars_equal_the_json_logs(pendulum_datasets, tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = tmp_path / "run"
    train(_config(pendulum_datasets["test/pendulum"]), run, loggers=("tensorboard",))
    acc = EventAccumulator(str(run / "tensorboard"))
    acc.Reload()
    metrics = _jsonl(run / "metrics.jsonl")
    key = next(k for k in metrics[0] if k != "step")
    events = acc.Scalars(key)
    assert [e.step for e in events] == [m["step"] for m in metrics]
    assert [e.value for e in events] == pytest.approx([m[key] for m in metrics], rel=1e-6)
    evals = _jsonl(run / "eval.jsonl")
    assert [e.value for e in acc.Scalars("eval/return")] == pytest.approx(
        [e["mean"] for e in evals]
    )


def test_wandb_offline_run_holds_the_last_metrics(pendulum_datasets, tmp_path, monkeypatch):
    """wandb's own run object (offline) receives every record: its summary, read just before
    the run finishes, holds the last metrics and evaluation; the run's log is on disk."""
    pytest.importorskip("wandb")
    import rlu.training.loggers

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    seen = {}
    flush = rlu.training.loggers.WandbLogger.flush

    def flush_then_read(self):
        flush(self)
        seen.update({k: self.run.summary[k] for k in self.run.summary.keys()})

    monkeypatch.setattr(rlu.training.loggers.WandbLogger, "flush", flush_then_read)
    run = tmp_path / "run"
    train(_config(pendulum_datasets["test/pendulum"]), run, loggers=("wandb",))
    last = _jsonl(run / "metrics.jsonl")[-1]
    for key, value in last.items():
        if key != "step":
            assert seen[key] == pytest.approx(value)
    assert seen["eval/return"] == pytest.approx(_jsonl(run / "eval.jsonl")[-1]["mean"])
    logs = list((run / "wandb").glob("offline-run-*/*.wandb"))
    assert len(logs) == 1 and logs[0].stat().st_size > 0


def test_an_unknown_logger_is_refused_before_the_run_folder_exists(pendulum_datasets, tmp_path):
    with pytest.raises(RluError, match="loggers are csv, tensorboard, wandb"):
        train(_config(pendulum_datasets["test/pendulum"]), tmp_path / "r", loggers=("mlflow",))
    assert not (tmp_path / "r").exists()
