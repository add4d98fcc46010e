"""Where a run's metrics go besides its own metrics.jsonl and eval.jsonl: CSV files, TensorBoard,
Weights & Biases. One small interface, one class each; the heavy ones behind extras.

``rlu train --log-to csv tensorboard wandb``. Every logger sees the same records the run writes
to its JSON-lines logs (``log(kind, record)`` with ``kind`` "metrics" or "eval"; a record is the
step and float values), so what it shows equals metrics.jsonl. Loggers do not change what a run
computes: they are not part of its config, and a resumed run may log elsewhere. A resumed run's
CSV files are cut back to the checkpoint's step, as its JSON-lines logs are.

- ``csv``: RUN/metrics.csv and RUN/eval.csv (mean return, episodes), standard library only;
- ``tensorboard``: RUN/tensorboard (``torch.utils.tensorboard``; the ``tensorboard`` extra);
- ``wandb``: a Weights & Biases run named after the run folder, its config the run's
  config.json (the ``wandb`` extra; ``WANDB_MODE=offline`` writes it under RUN/wandb without a
  network, to sync later with ``wandb sync``).
"""

from __future__ import annotations

import csv
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

from rlu.system import install_hint
from rlu.types import RluError

LOGGERS = ("csv", "tensorboard", "wandb")


class Logger(Protocol):
    """Receives a run's records as it writes them; ``close`` ends the run's logging."""

    def log(self, kind: str, record: Mapping[str, Any]) -> None: ...

    def close(self) -> None: ...


class CsvLogger:
    """RUN/metrics.csv (every metric of every logged step) and RUN/eval.csv (step, mean
    return, episodes); the columns are the first record's keys (an agent logs the same keys
    at every step)."""

    def __init__(self, run: Path, start: int):
        self.run = run
        self.files: dict[str, tuple[Any, Any]] = {}
        for kind in ("metrics", "eval"):
            path = run / f"{kind}.csv"
            if path.exists():  # resume: keep the rows logged up to the checkpoint
                with open(path, newline="") as fh:
                    rows = list(csv.DictReader(fh))
                kept = [r for r in rows if int(float(r["step"])) <= start]
                fields = list(rows[0]) if rows else None
                if fields:
                    with open(path, "w", newline="") as fh:
                        w = csv.DictWriter(fh, fields)
                        w.writeheader()
                        w.writerows(kept)
                    fh = open(path, "a", newline="")  # noqa: SIM115 (closed by close())
                    self.files[kind] = (fh, csv.DictWriter(fh, fields, extrasaction="ignore"))

    def log(self, kind: str, record: Mapping[str, Any]) -> None:
        row = dict(record)
        if kind == "eval":
            row = {"step": record["step"], "mean": record["mean"],
                   "episodes": len(record["returns"])}  # fmt: skip
        if kind not in self.files:
            fh = open(self.run / f"{kind}.csv", "w", newline="")  # noqa: SIM115
            writer = csv.DictWriter(fh, list(row), extrasaction="ignore")
            writer.writeheader()
            self.files[kind] = (fh, writer)
        fh, writer = self.files[kind]
        writer.writerow(row)
        fh.flush()

    def close(self) -> None:
        for fh, _ in self.files.values():
            fh.close()
        self.files.clear()


class TensorBoardLogger:
    """Scalars under RUN/tensorboard: each metric by its key, evaluations as ``eval/return``."""

    def __init__(self, run: Path, start: int):
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            hint = install_hint("tensorboard")
            raise RluError(f"--log-to tensorboard needs tensorboard: {hint}") from None
        purge = start + 1 if start else None  # a resumed run drops what followed its checkpoint
        self.writer = SummaryWriter(str(run / "tensorboard"), purge_step=purge)

    def log(self, kind: str, record: Mapping[str, Any]) -> None:
        step = int(record["step"])
        if kind == "eval":
            self.writer.add_scalar("eval/return", float(record["mean"]), step)
            return
        for key, value in record.items():
            if key != "step":
                self.writer.add_scalar(key, float(value), step)

    def close(self) -> None:
        self.writer.close()


class WandbLogger:
    """A Weights & Biases run (id and name from the run folder, so a resumed run continues it)."""

    def __init__(self, run: Path, start: int, config: Mapping[str, Any]):
        try:
            import wandb
        except ImportError:
            raise RluError(f"--log-to wandb needs wandb: {install_hint('wandb')}") from None
        run_id = "rlu-" + "".join(c if c.isalnum() else "-" for c in str(run.resolve()))[-100:]
        self.wandb = wandb
        self.run = wandb.init(
            project=os.environ.get("WANDB_PROJECT", "rlu"),
            name=run.name,
            id=run_id[-64:],
            dir=str(run),
            config=dict(config),
            resume="allow",
        )

    def log(self, kind: str, record: Mapping[str, Any]) -> None:
        step = int(record["step"])
        if kind == "eval":
            self.run.log({"eval/return": float(record["mean"])}, step=step)
            return
        self.run.log({k: float(v) for k, v in record.items() if k != "step"}, step=step)

    def flush(self) -> None:
        """Commit the last step's row (wandb keeps a step open until the next one)."""
        self.run.log({}, commit=True)

    def close(self) -> None:
        self.flush()
        self.run.finish()


def make_loggers(
    names: Sequence[str], run: Path, start: int, config: Mapping[str, Any]
) -> list[Any]:
    """The loggers ``names`` (``LOGGERS``) of run folder ``run``, resumed at ``start``."""
    out: list[Any] = []
    for name in names:
        if name == "csv":
            out.append(CsvLogger(run, start))
        elif name == "tensorboard":
            out.append(TensorBoardLogger(run, start))
        elif name == "wandb":
            out.append(WandbLogger(run, start, config))
        else:
            raise RluError(f"--log-to {name!r}; loggers are {', '.join(LOGGERS)}")
    return out
