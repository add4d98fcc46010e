"""Where a run's metrics go besides its own metrics.jsonl and eval.jsonl: CSV files, TensorBoard,
Weights & Biases. One small interface, one class each; the heavy ones behind extras.

``rlu train --log-to csv tensorboard wandb``. Every logger sees the same records the run writes
to its JSON-lines logs (``log(kind, record)`` with ``kind`` "metrics" or "eval"; a record is the
step and float values), so what it shows equals metrics.jsonl. Loggers do not change what a run
computes: they are not part of its config, and a resumed run may log elsewhere. A resumed run's
CSV files are cut back to the checkpoint's step, as its JSON-lines logs are.

- ``csv``: RUN/metrics.csv and RUN/eval.csv (mean return, episodes), standard library only;
- ``tensorboard``: RUN/tensorboard (``torch.utils.tensorboard``; the ``tensorboard`` extra);
- ``wandb``: a Weights & Biases run named after the run folder, its id kept in
  RUN/wandb_id.txt, its config the run's config.json (the ``wandb`` extra;
  ``WANDB_MODE=offline`` writes it under RUN/wandb without a network, to sync later with
  ``wandb sync``).
"""

from __future__ import annotations

import csv
import math
import os
import re
import secrets
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

from rlu import files
from rlu.system import install_hint
from rlu.types import FormatError, RluError

LOGGERS = ("csv", "tensorboard", "wandb")


class Logger(Protocol):
    """Receives a run's records as it writes them; ``close`` ends the run's logging."""

    def log(self, kind: str, record: Mapping[str, Any]) -> None: ...

    def close(self) -> None: ...


MAX_CSV_LINE = 1 << 20
"""Longest line of a metrics.csv / eval.csv rlu reads back on resume (its own lines are short)."""
FIX_CSV = "remove it to start the CSV afresh, or restore the file rlu wrote"


def _csv_rows(path: Path, start: int) -> Iterator[list[str]]:
    """The header, then every row logged at or before step ``start``, of a CSV log rlu wrote,
    streamed and checked: opened without following a link (a symbolic or hard link, a FIFO or
    a device is refused before any read), UTF-8 text, lines of at most ``MAX_CSV_LINE``, a
    ``step`` column of finite whole numbers >= 0, rows as wide as the header. A torn last line
    (a kill mid-row: no newline) is dropped."""
    try:
        fd = files.open_private(path, os.O_RDONLY | os.O_NONBLOCK, "CSV log")
    except OSError as e:
        raise RluError(f"{path}: cannot be read ({e.strerror}); {FIX_CSV}") from None
    with os.fdopen(fd, "r", encoding="utf-8", newline="") as fh:

        def lines() -> Iterator[str]:
            number = 0
            while True:
                try:
                    line = fh.readline(MAX_CSV_LINE + 1)
                except UnicodeDecodeError:
                    raise FormatError(
                        f"{path}: line {number + 1} is not UTF-8 text (a binary file?); {FIX_CSV}"
                    ) from None
                if not line:
                    return
                number += 1
                if len(line) > MAX_CSV_LINE:
                    raise FormatError(
                        f"{path}: line {number} is longer than {MAX_CSV_LINE:,} characters; "
                        f"{FIX_CSV}"
                    )
                if "\x00" in line:
                    raise FormatError(f"{path}: line {number} holds a NUL byte; {FIX_CSV}")
                if not line.endswith("\n"):
                    return  # torn by a kill mid-row
                yield line

        reader = csv.reader(lines())
        try:
            header = next(reader, None)
            if header is None:
                return
            if "step" not in header:
                raise FormatError(f"{path}: the header has no 'step' column; {FIX_CSV}")
            column = header.index("step")
            yield header
            for row in reader:
                where = f"{path}: line {reader.line_num}"
                try:
                    step = float(row[column]) if column < len(row) else math.nan
                except ValueError:
                    step = math.nan
                if not (math.isfinite(step) and step.is_integer() and step >= 0):
                    text = row[column] if column < len(row) else ""
                    raise FormatError(
                        f"{where}: field 'step' is {text[:40]!r}; expected a whole number >= 0; "
                        f"{FIX_CSV}"
                    )
                if step > start:
                    continue  # logged after the checkpoint: dropped, whatever its width
                if len(row) != len(header):
                    raise FormatError(
                        f"{where} has {len(row)} fields, the header {len(header)}; {FIX_CSV}"
                    )
                yield row
        except csv.Error as e:
            raise FormatError(
                f"{path}: line {reader.line_num} is not CSV ({e}); {FIX_CSV}"
            ) from None


def _check_folder(path: Path) -> None:
    """A logger's folder may be missing or a real folder, never a link out of the run."""
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise RluError(
            f"{path}: is a symbolic link or not a folder; rlu does not log through it: remove "
            "it and run again"
        )


class CsvLogger:
    """RUN/metrics.csv (every metric of every logged step) and RUN/eval.csv (step, mean
    return, episodes); the columns are the first record's keys (an agent logs the same keys
    at every step). Its files are opened only through :func:`rlu.files.open_private` and, on
    resume, read back streamed and checked (:func:`_csv_rows`) and cut through a temporary."""

    KINDS = ("metrics", "eval")

    @staticmethod
    def check(run: Path, start: int) -> None:
        """Refuse, before the run folder is written, a CSV log that resuming would fail on."""
        for kind in CsvLogger.KINDS:
            path = run / f"{kind}.csv"
            if os.path.lexists(path):
                for _ in _csv_rows(path, start):
                    pass

    def __init__(self, run: Path, start: int):
        self.run = run
        self.files: dict[str, tuple[Any, Any]] = {}
        for kind in self.KINDS:
            path = run / f"{kind}.csv"
            if not os.path.lexists(path):
                continue
            rows = _csv_rows(path, start)  # resume: keep the rows logged up to the checkpoint
            fields = next(rows, None)
            with files.atomic_path(path, root=run) as tmp:
                fd = os.open(tmp, os.O_WRONLY | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC)
                with os.fdopen(fd, "w", newline="") as out:
                    w = csv.writer(out)
                    if fields:
                        w.writerow(fields)
                        w.writerows(rows)
            if fields:
                fh = self._open(path, os.O_APPEND)
                self.files[kind] = (fh, csv.DictWriter(fh, fields, extrasaction="ignore"))

    @staticmethod
    def _open(path: Path, flag: int) -> Any:
        fd = files.open_private(path, os.O_WRONLY | os.O_CREAT | flag, "CSV log")
        return os.fdopen(fd, "a" if flag == os.O_APPEND else "w", newline="")

    def log(self, kind: str, record: Mapping[str, Any]) -> None:
        row = dict(record)
        if kind == "eval":
            row = {"step": record["step"], "mean": record["mean"],
                   "episodes": len(record["returns"])}  # fmt: skip
        if kind not in self.files:
            fh = self._open(self.run / f"{kind}.csv", os.O_TRUNC)
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

    @staticmethod
    def check(run: Path, start: int) -> None:
        _check_folder(run / "tensorboard")

    def __init__(self, run: Path, start: int):
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            hint = install_hint("tensorboard")
            raise RluError(f"--log-to tensorboard needs tensorboard: {hint}") from None
        folder = files.make_folder(run / "tensorboard", root=run)
        purge = start + 1 if start else None  # a resumed run drops what followed its checkpoint
        self.writer = SummaryWriter(str(folder), purge_step=purge)

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


WANDB_ID = "wandb_id.txt"
"""The file of a run folder holding its W&B run id (drawn at random when the run first logs to
W&B; a resumed run, wherever its folder now lies, continues that W&B run)."""
_WANDB_ID = re.compile(r"rlu-[0-9a-f]{16}")
WANDB_LOGIN = (
    "run `wandb login`, set WANDB_API_KEY, or set WANDB_MODE=offline to log under RUN/wandb "
    "and sync later"
)

WANDB_MODES = ("online", "offline", "disabled", "dryrun", "run", "shared")
"""The values of WANDB_MODE wandb takes (``wandb.sdk.wandb_settings.Settings.mode``, wandb 0.31;
exact, lower case); another is refused before a run folder is made, where wandb would refuse it
from inside ``wandb.init``."""


def _wandb_mode() -> str | None:
    """WANDB_MODE, checked: unset (None) or one of ``WANDB_MODES``."""
    mode = os.environ.get("WANDB_MODE")
    if mode is not None and mode not in WANDB_MODES:
        raise RluError(
            f"--log-to wandb: WANDB_MODE is {mode[:40]!r}; wandb takes {', '.join(WANDB_MODES)} "
            "(offline: log under RUN/wandb and sync later); set one or unset WANDB_MODE"
        )
    return mode


def _wandb_logged_in() -> bool:
    """Whether wandb would find a key (or needs none): WANDB_API_KEY, an offline or disabled
    WANDB_MODE, or the login ``wandb login`` keeps in ~/.netrc (or $NETRC)."""
    import netrc
    from urllib.parse import urlparse

    if os.environ.get("WANDB_API_KEY"):
        return True
    if _wandb_mode() in ("offline", "disabled", "dryrun"):
        return True
    host = urlparse(os.environ.get("WANDB_BASE_URL", "https://api.wandb.ai")).hostname
    path = os.environ.get("NETRC") or os.path.join(os.path.expanduser("~"), ".netrc")
    try:
        return netrc.netrc(path).authenticators(host or "api.wandb.ai") is not None
    except (OSError, netrc.NetrcParseError):
        return False


def _wandb_id(run: Path, create: bool) -> str | None:
    path = run / WANDB_ID
    fix = f"remove {WANDB_ID} (the run then logs to a new W&B run)"
    if not os.path.lexists(path):
        if not create:
            return None
        run_id = "rlu-" + secrets.token_hex(8)
        files.write_atomic(path, run_id + "\n", root=run)
        return run_id
    files.check_target(path, run)
    text = files.read_bytes(path, 256, fix).decode("ascii", "replace").strip()
    if not _WANDB_ID.fullmatch(text):
        raise FormatError(f"{path}: {text[:40]!r} is not a W&B run id rlu wrote; {fix}")
    return text


class WandbLogger:
    """A Weights & Biases run; its id is drawn once and kept in RUN/wandb_id.txt, so a resumed
    run continues it (and only it: the id does not depend on where the folder lies)."""

    @staticmethod
    def check_settings() -> None:
        """What no run folder changes: WANDB_MODE is one wandb takes, a key is configured (or
        the mode needs none)."""
        _wandb_mode()
        if not _wandb_logged_in():
            raise RluError(f"--log-to wandb: no W&B API key is configured; {WANDB_LOGIN}")

    @staticmethod
    def check(run: Path, start: int) -> None:
        WandbLogger.check_settings()
        _check_folder(run / "wandb")
        _wandb_id(run, create=False)

    def __init__(self, run: Path, start: int, config: Mapping[str, Any]):
        try:
            import wandb
        except ImportError:
            raise RluError(f"--log-to wandb needs wandb: {install_hint('wandb')}") from None
        files.make_folder(run / "wandb", root=run)
        run_id = _wandb_id(run, create=True)
        self.wandb = wandb
        try:
            self.run = wandb.init(
                project=os.environ.get("WANDB_PROJECT", "rlu"),
                name=run.name,
                id=run_id,
                dir=str(run),
                config=dict(config),
                resume="allow",
            )
        except wandb.errors.Error as e:
            raise RluError(f"--log-to wandb: wandb refused to start ({e}); {WANDB_LOGIN}") from None

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


_CLASSES: dict[str, type[CsvLogger | TensorBoardLogger | WandbLogger]] = {
    "csv": CsvLogger,
    "tensorboard": TensorBoardLogger,
    "wandb": WandbLogger,
}


def check_loggers(names: Sequence[str], run: Path, start: int) -> None:
    """Refuse, before a run folder is written, what its loggers ``names`` would fail on: an
    unknown name, a CSV log that does not read back, a logger folder that is a link, an unknown
    WANDB_MODE, W&B without a key."""
    for name in names:
        if name not in _CLASSES:
            raise RluError(f"--log-to {name!r}; loggers are {', '.join(LOGGERS)}")
        _CLASSES[name].check(run, start)


def check_logger_settings(names: Sequence[str]) -> None:
    """Refuse what loggers ``names`` would fail on whatever the run folder: an unknown name, an
    unknown WANDB_MODE, W&B without a key (a sweep checks them before it makes its folder)."""
    for name in names:
        if name not in _CLASSES:
            raise RluError(f"--log-to {name!r}; loggers are {', '.join(LOGGERS)}")
        if name == "wandb":
            WandbLogger.check_settings()


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
