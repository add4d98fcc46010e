"""Writes through planted links and into the wrong places (issue 39, third round, item 1): a
symbolic or hard link planted at a run's CSV logs on resume, at its TensorBoard / W&B folder, at
a report's files or at a video's; output folders that are inputs (the dataset, the run, its
checkpoints), empty names, an unrelated folder. Each is one line ``rlu: error: ...`` and exit
code 2 from ``rlu.cli.main``, and nothing under the test's folder changes: not the link's
target, not the files written before it. (The export and import outputs are
tests/hostile/test_interop_outputs.py's.)"""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import pytest

pytest.importorskip("torch")
pytest.importorskip("gymnasium")

from rlu.cli import main  # noqa: E402
from tests.train.pendulum import write_dataset  # noqa: E402

ENV = "tests.train.pendulum:make_env"


def _train_argv(ds: Path, out: Path, *more: str) -> list[str]:
    return ["train", "--task", "test/pendulum", "--agent", "tests.train.fake_agent",
            "--dataset", str(ds), "--env", ENV, "--steps", "20", "--checkpoint-every", "10",
            "--eval-every", "10", "--eval-episodes", "1", "--eval-envs", "1",
            "--eval-max-steps", "5", "--no-progress", "--out", str(out), *more]  # fmt: skip


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A pendulum dataset and a finished 20-step run of the fake agent with CSV logs, two
    evaluations and a report of its own."""
    root = tmp_path_factory.mktemp("round3_links")
    ds = write_dataset(root / "ds", "test/pendulum", episodes=3)
    run = root / "run"
    assert main(_train_argv(ds, run, "--log-to", "csv")) == 0
    assert main(["report", str(run)]) == 0
    return ds, run


def _snapshot(root: Path) -> dict[str, str]:
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_symlink():
            out[str(p.relative_to(root))] = "-> " + os.readlink(p)
        elif p.is_file():
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def refused(capsys, argv: list[str], roots: list[Path], *words: str) -> str:
    capsys.readouterr()
    before = [_snapshot(r) for r in roots]
    code = main(argv)
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if not x.startswith("rlu train: ")]
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("rlu: error: "), err
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], lines[0]
    assert [_snapshot(r) for r in roots] == before  # nothing written, replaced or left over
    return lines[0]


def _resumable(run: Path, dest: Path) -> Path:
    """A copy of ``run`` cut back to its first checkpoint (step 10), as a kill would leave it."""
    shutil.copytree(run, dest, symlinks=True)
    (dest / "result.json").unlink()
    (dest / "checkpoints" / "step_00000020.pt").unlink()
    return dest


def _plant(path: Path, target: Path, kind: str) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif os.path.lexists(path):
        path.unlink()
    if kind == "symlink":
        path.symlink_to(target)
    else:
        os.link(target, path)


@pytest.mark.parametrize("kind", ["symlink", "hardlink"])
@pytest.mark.parametrize("name", ["metrics.csv", "eval.csv"])
def test_a_link_at_a_csv_log_is_not_written_through_on_resume(made, tmp_path, capsys, name, kind):
    ds, run = made
    work = _resumable(run, tmp_path / "run")
    victim = tmp_path / "victim.csv"
    victim.write_text("step,x\n1,2\n")
    _plant(work / name, victim, kind)
    argv = _train_argv(ds, work, "--log-to", "csv", "--resume")
    refused(capsys, argv, [tmp_path], name, "link")


@pytest.mark.parametrize("logger", ["tensorboard", "wandb"])
def test_a_linked_logger_folder_is_not_followed(made, tmp_path, capsys, monkeypatch, logger):
    ds, run = made
    monkeypatch.setenv("WANDB_MODE", "offline")
    work = _resumable(run, tmp_path / "run")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (work / logger).symlink_to(elsewhere)
    argv = _train_argv(ds, work, "--log-to", logger, "--resume")
    refused(capsys, argv, [tmp_path], f"{logger}: is a symbolic link")
    assert not any(elsewhere.iterdir())


REPORT_FILES = [
    "report.md",
    "report.html",
    "report.json",
    "figures/other_tasks.png",
    "figures/other_curves.png",
]


@pytest.mark.parametrize("kind", ["symlink", "hardlink"])
@pytest.mark.parametrize("name", REPORT_FILES)
def test_a_link_in_the_report_folder_is_not_written_through(made, tmp_path, capsys, name, kind):
    _, run = made
    work = tmp_path / "run"
    shutil.copytree(run, work, symlinks=True)
    assert (work / "report" / name).is_file(), sorted((work / "report").rglob("*"))
    if name != "report.md":  # what an earlier report left: replaced only if all can be
        (work / "report" / "report.md").write_text("the earlier report")
    victim = tmp_path / "victim"
    victim.write_text("precious")
    _plant(work / "report" / name, victim, kind)
    refused(capsys, ["report", str(work)], [tmp_path], "report")
    assert victim.read_text() == "precious"


def test_a_linked_figures_folder_is_not_followed(made, tmp_path, capsys):
    _, run = made
    work = tmp_path / "run"
    shutil.copytree(run, work, symlinks=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    _plant(work / "report" / "figures", elsewhere, "symlink")
    refused(capsys, ["report", str(work)], [tmp_path], "figures", "symbolic link")
    assert not any(elsewhere.iterdir())


@pytest.mark.parametrize(
    ("out", "says"),
    [
        ("", "--out is empty"),
        ("{ds}", "the input"),
        ("{run}", "the input"),
        ("{run}/checkpoints", "the input"),
        ("{link}", "choose another report folder"),
        ("{unrelated}", "not an rlu report folder"),
        ("{unrelated_json}", "did not write"),
    ],
    ids=["empty", "dataset", "run", "checkpoints", "linked_folder", "unrelated", "foreign_json"],
)
def test_a_report_out_in_the_wrong_place_is_refused(made, tmp_path, capsys, out, says):
    ds, run = made
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "link").symlink_to(elsewhere)
    kept = {"unrelated": ["report.md"], "unrelated_json": ["report.md", "report.json"]}
    for name, files in kept.items():
        (tmp_path / name).mkdir()
        for f in files:
            (tmp_path / name / f).write_text('{"mine": 1}')
    target = out.format(ds=ds, run=run, link=tmp_path / "link", unrelated=tmp_path / "unrelated",
                        unrelated_json=tmp_path / "unrelated_json")  # fmt: skip
    refused(capsys, ["report", str(run), "--out", target], [tmp_path, ds, run], says)


def test_a_report_out_in_a_sweep_is_refused(made, tmp_path, capsys):
    """A sweep folder (its sweep.json) as the report's --out, for another input."""
    _, run = made
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "sweep.json").write_text("{}")
    refused(capsys, ["report", str(run), "--out", str(sweep)], [tmp_path, run], "--out")


@pytest.mark.parametrize(
    ("video", "says"),
    [
        ("", "--video is empty"),
        ("{ds}", "the input"),
        ("{run}", "the input"),
        ("{run}/checkpoints", "the input"),
        ("{link}", "symbolic link"),
        ("{unrelated}", "not an rlu video folder"),
    ],
    ids=["empty", "dataset", "run", "checkpoints", "linked_folder", "unrelated"],
)
def test_a_video_folder_in_the_wrong_place_is_refused(made, tmp_path, capsys, video, says):
    ds, run = made
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "link").symlink_to(elsewhere)
    (tmp_path / "unrelated").mkdir()
    (tmp_path / "unrelated" / "notes.txt").write_text("mine")
    target = video.format(ds=ds, run=run, link=tmp_path / "link", unrelated=tmp_path / "unrelated")
    argv = ["evaluate", str(run), "--episodes", "1", "--video", target]
    refused(capsys, argv, [tmp_path, ds, run], says)


@pytest.mark.parametrize("kind", ["symlink", "hardlink"])
@pytest.mark.parametrize("name", ["episode_001.mp4", "videos.json"])
def test_a_link_at_a_later_video_is_refused_before_any_is_written(tmp_path, name, kind):
    """The recorder checks every file it will replace before it films: a link at the second
    episode's video (or at the index) leaves the first one's file as it was."""
    from rlu.evaluation.video import Recorder
    from rlu.types import RluError

    pytest.importorskip("imageio_ffmpeg")
    out = tmp_path / "videos"
    out.mkdir()
    (out / "episode_000.mp4").write_bytes(b"old video")
    victim = tmp_path / "victim"
    victim.write_text("precious")
    _plant(out / name, victim, kind)
    before = _snapshot(tmp_path)
    with pytest.raises(RluError, match=name):
        Recorder(out, 2, fmt="mp4")
    assert _snapshot(tmp_path) == before
