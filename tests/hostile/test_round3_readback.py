"""rlu's own files read back on resume (issue 39, third round, item 3): a metrics.csv / eval.csv
whose step is not a whole number, that lacks the step column, is binary, holds an overlong
field or is a FIFO is one line ``rlu: error: ...`` (exit 2) naming the file, before the run
folder is touched; W&B without a key is one line saying how to log in (no network: the key is
looked for before wandb starts); the W&B run id is drawn once and kept in the run folder.
(fqe.json's NaN is written as null on main: runs.read_fqe's tests.)"""

from __future__ import annotations

import os
import shutil

import pytest

from tests.hostile.test_round3_links import _resumable, _train_argv, made, refused

__all__ = ["made"]  # the module-scoped run, shared with the links tests' definition

GOOD = "step,loss\n10,0.5\n"


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("step,loss\nabc,0.5\n", "field 'step' is 'abc'"),
        ("step,loss\nnan,0.5\n", "field 'step' is 'nan'"),
        ("step,loss\ninf,0.5\n", "field 'step' is 'inf'"),
        ("step,loss\n-3,0.5\n", "field 'step' is '-3'"),
        ("step,loss\n2.5,0.5\n", "field 'step' is '2.5'"),
        ("loss,other\n0.5,1\n", "no 'step' column"),
        (b"\x89PNG\r\n\x1a\n\xff\xfe\x00\x01\n", "not UTF-8"),
        ("step,loss\n1,\x00\n", "NUL"),
        ("step,loss\n1," + "x" * 200_000 + "\n", "not CSV"),
        ("step,loss\n1," + "x" * (1 << 20) + "\n", "longer than"),
        ("step,loss\n5,0.5,9\n", "has 3 fields"),
    ],
    ids=["abc", "nan", "inf", "negative", "fraction", "no_step", "binary", "nul", "long_field",
         "long_line", "wide_row"],
)  # fmt: skip
@pytest.mark.parametrize("name", ["metrics.csv", "eval.csv"])
def test_a_damaged_csv_log_is_one_line_on_resume(made, tmp_path, capsys, name, text, says):
    ds, run = made
    work = _resumable(run, tmp_path / "run")
    path = work / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    refused(capsys, _train_argv(ds, work, "--log-to", "csv", "--resume"), [tmp_path], name, says)


def test_a_fifo_at_a_csv_log_is_refused_without_hanging(made, tmp_path, capsys):
    ds, run = made
    work = _resumable(run, tmp_path / "run")
    (work / "metrics.csv").unlink()
    os.mkfifo(work / "metrics.csv")
    argv = _train_argv(ds, work, "--log-to", "csv", "--resume")
    refused(capsys, argv, [tmp_path], "metrics.csv", "not a plain file")


def test_rows_after_the_checkpoint_are_dropped_whatever_they_hold(made, tmp_path, capsys):
    """A torn last row and rows logged after the checkpoint are cut, not refused."""
    from rlu.cli import main

    ds, run = made
    work = _resumable(run, tmp_path / "run")
    with open(work / "metrics.csv", "a") as fh:
        fh.write("15,1,2,3\n18,0.")  # too wide, after step 10; torn
    assert main(_train_argv(ds, work, "--log-to", "csv", "--resume")) == 0
    assert (work / "metrics.csv").read_text() == (run / "metrics.csv").read_text()


def _no_wandb_login(monkeypatch, tmp_path):
    pytest.importorskip("wandb")
    for var in ("WANDB_API_KEY", "WANDB_MODE", "WANDB_BASE_URL"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("NETRC", str(tmp_path / "home" / ".netrc"))


def test_wandb_without_a_key_is_one_line_before_the_run_folder(made, tmp_path, capsys, monkeypatch):
    ds, _ = made
    _no_wandb_login(monkeypatch, tmp_path)
    line = refused(capsys, _train_argv(ds, tmp_path / "new", "--log-to", "wandb"), [tmp_path])
    for words in ("wandb login", "WANDB_API_KEY", "WANDB_MODE=offline"):
        assert words in line
    assert not (tmp_path / "new").exists()


def test_wandb_refusing_to_start_is_one_line(made, tmp_path, capsys, monkeypatch):
    """A key that passes rlu's look-up but that wandb refuses: its error, as one line."""
    ds, _ = made
    _no_wandb_login(monkeypatch, tmp_path)
    import wandb

    import rlu.training.loggers

    def refuse(**kw):
        raise wandb.errors.UsageError("api_key not valid")

    monkeypatch.setattr(rlu.training.loggers, "_wandb_logged_in", lambda: True)
    monkeypatch.setattr(wandb, "init", refuse)
    line = refused(capsys, _train_argv(ds, tmp_path / "new", "--log-to", "wandb"), [])
    assert "api_key not valid" in line and "wandb login" in line


def test_the_wandb_id_is_kept_in_the_run_folder(made, tmp_path, monkeypatch):
    """The id is drawn once, kept in RUN/wandb_id.txt and reused wherever the folder moves."""
    pytest.importorskip("wandb")
    import wandb

    import rlu.training.loggers

    ds, _ = made
    ids = []

    class Run:
        def log(self, *a, **kw):
            pass

        def finish(self):
            pass

    def init(**kw):
        ids.append(kw["id"])
        return Run()

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setattr(wandb, "init", init)
    from rlu.cli import main

    first = tmp_path / "first"
    assert main(_train_argv(ds, first, "--log-to", "wandb")) == 0
    kept = (first / rlu.training.loggers.WANDB_ID).read_text().strip()
    moved = _resumable(first, tmp_path / "moved")
    shutil.rmtree(first)
    assert main(_train_argv(ds, moved, "--log-to", "wandb", "--resume")) == 0
    assert ids == [kept, kept] and kept.startswith("rlu-") and str(tmp_path) not in kept


def test_a_forged_wandb_id_is_refused(made, tmp_path, capsys, monkeypatch):
    ds, run = made
    monkeypatch.setenv("WANDB_MODE", "offline")
    work = _resumable(run, tmp_path / "run")
    (work / "wandb_id.txt").write_text("../../etc\n")
    argv = _train_argv(ds, work, "--log-to", "wandb", "--resume")
    refused(capsys, argv, [tmp_path], "wandb_id.txt", "not a W&B run id")


def _fifo(path):
    os.mkfifo(path)


@pytest.mark.parametrize(
    ("write", "says"),
    [
        (lambda p: p.write_text("{not json"), "not valid JSON"),
        (lambda p: p.write_text("[1, 2]"), "not"),
        (_fifo, "not a regular file"),
        (lambda p: None, "is missing"),
    ],
    ids=["junk", "a_list", "fifo", "missing"],
)
@pytest.mark.parametrize("reader", ["reference_scores", "best_behaviour", "random_scores"])
def test_a_score_file_of_the_users_is_read_bounded_with_a_clear_error(tmp_path, reader, write,
                                                                      says):  # fmt: skip
    """The reference, best-behaviour and random-score files a user passes are rlu's own formats
    read back: a FIFO never hangs, junk or a list is a FormatError naming the file, never a
    traceback."""
    from rlu.envs import scores
    from rlu.evaluation import reference
    from rlu.evaluation.scores import load_reference_scores
    from rlu.types import RluError

    path = tmp_path / "scores.json"
    write(path)
    load = {"reference_scores": lambda: load_reference_scores(str(path)),
            "best_behaviour": lambda: reference.load(path),
            "random_scores": lambda: scores.load(path)}[reader]  # fmt: skip
    with pytest.raises(RluError, match=says) as e:
        load()
    assert str(path) in str(e.value) or "reference scores" in str(e.value)
