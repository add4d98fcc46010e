"""The one guarded writer (rlu.files): planted links, hard links and symlinked folders refused,
temporaries unpredictable and exclusive, nothing left behind on failure."""

from __future__ import annotations

import errno
import os

import pytest

from rlu.files import (
    atomic_path,
    check_target,
    clear_temporaries,
    make_folder,
    move_into_place,
    write_atomic,
    write_json,
)
from rlu.types import RluError


def test_writes_and_replaces_a_plain_file(tmp_path):
    target = tmp_path / "report.md"
    write_atomic(target, "one")
    write_atomic(target, "two")
    assert target.read_text() == "two"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.md"]


def test_symlink_at_target_is_refused_and_its_target_untouched(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    (tmp_path / "report.md").symlink_to(victim)
    with pytest.raises(RluError, match="symbolic link"):
        write_atomic(tmp_path / "report.md", "overwritten?")
    assert victim.read_text() == "precious"
    assert (tmp_path / "report.md").is_symlink()


def test_hard_link_at_target_is_refused(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    os.link(victim, tmp_path / "metrics.csv")
    with pytest.raises(RluError, match="hard link"):
        write_atomic(tmp_path / "metrics.csv", "x")
    assert victim.read_text() == "precious"


def test_folder_or_fifo_at_target_is_refused(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(RluError, match="not a plain file"):
        write_atomic(tmp_path / "d", "x")
    os.mkfifo(tmp_path / "fifo")
    with pytest.raises(RluError, match="not a plain file"):
        write_atomic(tmp_path / "fifo", "x")


def test_symlinked_folder_below_root_is_refused(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    root = tmp_path / "out"
    root.mkdir()
    (root / "figures").symlink_to(outside)
    with pytest.raises(RluError, match="symbolic link"):
        write_atomic(root / "figures" / "a.png", b"png", root=root)
    assert not any(outside.iterdir())
    # the root itself a link: refused too
    (tmp_path / "link_out").symlink_to(outside)
    with pytest.raises(RluError, match="symbolic link"):
        write_atomic(tmp_path / "link_out" / "a.png", b"png", root=tmp_path / "link_out")
    assert not any(outside.iterdir())


def test_path_outside_root_is_refused(tmp_path):
    with pytest.raises(RluError, match="outside the output folder"):
        check_target(tmp_path / "elsewhere" / "x", root=tmp_path / "out")


def test_temporary_is_unpredictable_keeps_suffix_and_is_removed_on_failure(tmp_path):
    target = tmp_path / "video.mp4"
    names = []
    for _ in range(2):
        with pytest.raises(ZeroDivisionError):
            with atomic_path(target, suffix=True) as tmp:
                names.append(tmp.name)
                assert tmp.exists() and tmp.suffix == ".mp4"
                raise ZeroDivisionError
    assert names[0] != names[1]
    assert not any(tmp_path.iterdir())


def test_planted_link_at_a_guessed_temporary_name_is_never_written(tmp_path):
    victim = tmp_path / "victim"
    victim.write_text("precious")
    # the old fixed name was .NAME.PID.tmp: plant it; the writer picks another name
    (tmp_path / f".r.json.{os.getpid()}.tmp").symlink_to(victim)
    write_json(tmp_path / "r.json", {"a": 1})
    assert victim.read_text() == "precious"


def test_nan_is_refused_by_write_json(tmp_path):
    with pytest.raises(RluError, match="NaN or infinite"):
        write_json(tmp_path / "fqe.json", {"value": float("nan")})
    assert not any(tmp_path.iterdir())


def test_make_folder_refuses_links_and_files(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (tmp_path / "tb").symlink_to(outside)
    with pytest.raises(RluError, match="symbolic link"):
        make_folder(tmp_path / "tb")
    (tmp_path / "file").write_text("x")
    with pytest.raises(RluError, match="not a folder"):
        make_folder(tmp_path / "file")
    made = make_folder(tmp_path / "a" / "b")
    assert made.is_dir()


def test_clear_temporaries_removes_only_temporaries(tmp_path):
    keep = tmp_path / "keep.txt"
    keep.write_text("x")
    (tmp_path / ".a.json.0123abcd.tmp").write_text("")
    (tmp_path / ".video.0123abcd.tmp.mp4").write_text("")
    (tmp_path / ".hidden").write_text("mine")
    clear_temporaries(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".hidden", "keep.txt"]


def test_output_file_rules(tmp_path):
    from rlu.files import check_output, check_output_file

    with pytest.raises(RluError, match="empty"):
        check_output_file("")
    with pytest.raises(RluError, match="empty"):
        check_output("")
    ds = tmp_path / "ds"
    ds.mkdir()
    with pytest.raises(RluError, match="inside the input"):
        check_output_file(ds / "policies" / "x.npz", [ds])
    other = tmp_path / "other.hdf5"
    other.write_bytes(b"someone else's")
    with pytest.raises(RluError, match="--overwrite"):
        check_output_file(other)
    with pytest.raises(RluError, match="not written by rlu"):
        check_output_file(other, overwrite=True, ours=lambda p: False)
    assert check_output_file(other, overwrite=True, ours=lambda p: True) == other
    assert check_output_file(tmp_path / "new.npz") == tmp_path / "new.npz"


def test_move_into_place_checks_the_target_as_every_write_does(tmp_path):
    """The rename of a temporary or a staging folder into place (the dataset writer, a
    conversion's parts, a download, a record file, a Minari export) refuses a planted link at
    the target, a linked folder on the way and a planted source, and writes through none."""
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "keep").write_text("keep")
    tmp = tmp_path / ".f.tmp"
    tmp.write_text("new")
    (tmp_path / "f").symlink_to(victim / "keep")
    with pytest.raises(RluError, match="is a symbolic link"):
        move_into_place(tmp, tmp_path / "f")
    staged = tmp_path / ".ds.partial"
    staged.mkdir()
    (staged / "data").write_text("rows")
    (tmp_path / "ds").symlink_to(victim, target_is_directory=True)
    with pytest.raises(RluError, match="is a symbolic link"):
        move_into_place(staged, tmp_path / "ds")
    with pytest.raises(RluError, match="is a symbolic link"):  # a linked folder below root
        move_into_place(staged, tmp_path / "ds" / "inner", tmp_path)
    (tmp_path / "plain").write_text("a file")
    with pytest.raises(RluError, match="not a folder"):
        move_into_place(staged, tmp_path / "plain")
    (tmp_path / ".planted").symlink_to(victim)
    with pytest.raises(RluError, match="not the temporary"):
        move_into_place(tmp_path / ".planted", tmp_path / "elsewhere")
    assert sorted(p.name for p in victim.iterdir()) == ["keep"]
    assert (victim / "keep").read_text() == "keep" and (tmp_path / "f").is_symlink()
    # into place: a file over a plain file, a folder onto a free name; a non-empty folder there
    # is the caller's (another writer finished first)
    (tmp_path / "f").unlink()
    (tmp_path / "f").write_text("old")
    assert move_into_place(tmp, tmp_path / "f").read_text() == "new" and not tmp.exists()
    assert (move_into_place(staged, tmp_path / "ds2") / "data").read_text() == "rows"
    again = tmp_path / ".again"
    again.mkdir()
    (again / "data").write_text("rows")
    with pytest.raises(OSError) as e:
        move_into_place(again, tmp_path / "ds2")
    assert e.value.errno in (errno.ENOTEMPTY, errno.EEXIST)
