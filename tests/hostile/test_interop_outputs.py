"""Hostile outputs of ``rlu export`` / ``rlu import`` (issue 39 items 1 and 2, the interop part):
an output inside the input dataset (its policies, its steps), '' as a name, an unrelated existing
.hdf5 / .npz / .h5 (with and without --overwrite), planted symbolic and hard links at the output,
at its sidecar and at the old fixed-name temporary, ``--minari-dir`` inside the dataset, an import
``--out`` inside its source. Each is one clear line and exit code 2, never a traceback, and
changes nothing on disk; rlu's own export is replaced with --overwrite, and ``-o`` into a folder
that does not exist yet makes it."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("h5py")

from rlu.cli import main  # noqa: E402
from rlu.data import DatasetWriter, Schema, open_dataset  # noqa: E402
from rlu.data.synthetic import random_episodes  # noqa: E402
from rlu.data.validate import validate  # noqa: E402
from rlu.tasks import get_task  # noqa: E402

TASK = "control_suite/cartpole_swingup"
POLICY = "policies/run_000/checkpoint_00000"


@pytest.fixture
def ds(tmp_path) -> Path:
    """A dataset with an attached behaviour policy (``policies/...``), as ``rlu generate``
    keeps them."""
    schema = Schema.for_task(get_task(TASK))
    np.savez(tmp_path / "p.npz", w=np.arange(6.0))
    (tmp_path / "p.json").write_text(
        json.dumps({"arrays": {"w": {"shape": [6], "dtype": "float64"}}})
    )
    with DatasetWriter(tmp_path / "ds", schema, {"source": "test"}) as w:
        w.extend(random_episodes(schema, 3, 5, seed=0))
        w.attach(f"{POLICY}.npz", tmp_path / "p.npz")
        w.attach(f"{POLICY}.json", tmp_path / "p.json")
    (tmp_path / "p.npz").unlink()
    (tmp_path / "p.json").unlink()
    return tmp_path / "ds"


def snapshot(root: Path) -> dict[str, str]:
    """Every file under ``root`` (links as links) and its content's hash."""
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_symlink():
            out[str(p.relative_to(root))] = "-> " + os.readlink(p)
        elif p.is_file():
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def refused(capsys, argv: list[str], root: Path, *words: str) -> None:
    before = snapshot(root)
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("rlu: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for w in words:
        assert w in err, err
    assert snapshot(root) == before  # nothing written, nothing replaced, nothing left over


def export(ds: Path, fmt: str, *more: str) -> list[str]:
    return ["export", str(ds), "--format", fmt, *more]


@pytest.mark.parametrize(
    ("fmt", "rel"),
    [
        ("d4rl", f"{POLICY}.npz"),
        ("d4rl", "steps/extra.hdf5"),
        ("d3rlpy", "steps/reward.h5"),
        ("d4rl", "manifest.npz"),
    ],
)
def test_an_output_inside_the_input_dataset_is_refused(ds, capsys, fmt, rel):
    refused(capsys, export(ds, fmt, "-o", str(ds / rel)), ds.parent, "lies inside the input")
    assert validate(ds).ok


@pytest.mark.parametrize("fmt", ["d4rl", "d3rlpy"])
def test_an_empty_output_name_is_refused(ds, capsys, fmt):
    refused(capsys, export(ds, fmt, "-o", ""), ds.parent, "is empty")


@pytest.mark.parametrize(
    ("fmt", "name"), [("d4rl", "x.hdf5"), ("d4rl", "x.npz"), ("d3rlpy", "x.h5")]
)
def test_an_unrelated_existing_file_is_never_replaced(ds, tmp_path, capsys, fmt, name):
    import h5py

    other = tmp_path / name
    if name.endswith(".npz"):
        np.savez(other, mine=np.arange(3))
    else:
        with h5py.File(other, "w") as f:
            f["mine"] = np.arange(3)
    refused(capsys, export(ds, fmt, "-o", str(other)), tmp_path, "exists", "--overwrite")
    refused(capsys, export(ds, fmt, "-o", str(other), "--overwrite"), tmp_path,
            "was not written by rlu")  # fmt: skip


@pytest.mark.parametrize(
    ("fmt", "name"), [("d4rl", "x.hdf5"), ("d4rl", "x.npz"), ("d3rlpy", "x.h5")]
)
def test_overwrite_replaces_rlus_own_export(ds, tmp_path, capsys, fmt, name):
    out = tmp_path / "new" / "deeper" / name  # a folder that does not exist yet is made
    assert main(export(ds, fmt, "-o", str(out))) == 0
    first = out.read_bytes()
    refused(capsys, export(ds, fmt, "-o", str(out)), tmp_path, "exists", "--overwrite")
    assert main(export(ds, fmt, "-o", str(out), "--overwrite")) == 0
    assert out.read_bytes() != first  # a new export id
    assert "note: " in capsys.readouterr().out  # the one line saying what the sidecar keeps
    names = sorted(p.name for p in out.parent.iterdir())
    assert names == sorted([name, name + ".rlu.npz"])  # no temporaries left


@pytest.mark.parametrize("fmt", ["d4rl", "d3rlpy"])
def test_planted_links_are_refused(ds, tmp_path, capsys, fmt):
    name = "x.hdf5" if fmt == "d4rl" else "x.h5"
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "out"
    out.mkdir()
    (out / name).symlink_to(victim)
    refused(capsys, export(ds, fmt, "-o", str(out / name), "--overwrite"), tmp_path,
            "symbolic link")  # fmt: skip
    (out / name).unlink()
    os.link(victim, out / name)
    refused(capsys, export(ds, fmt, "-o", str(out / name), "--overwrite"), tmp_path,
            "hard link")  # fmt: skip
    (out / name).unlink()
    (out / f"{name}.rlu.npz").symlink_to(victim)  # the sidecar's name
    refused(capsys, export(ds, fmt, "-o", str(out / name)), tmp_path, "symbolic link")
    assert victim.read_text() == "precious"


@pytest.mark.parametrize("fmt", ["d4rl", "d3rlpy"])
def test_the_old_fixed_temporary_name_is_not_written_through(ds, tmp_path, capsys, fmt):
    """Exports used to write ``.NAME.partial.SUFFIX``; a link planted there is left alone."""
    name = "x.hdf5" if fmt == "d4rl" else "x.h5"
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "out"
    out.mkdir()
    (out / f".{name}.partial{Path(name).suffix}").symlink_to(victim)
    assert main(export(ds, fmt, "-o", str(out / name))) == 0
    assert victim.read_text() == "precious"
    assert os.path.islink(out / f".{name}.partial{Path(name).suffix}")


def test_minari_dir_inside_the_dataset_is_refused(ds, capsys):
    pytest.importorskip("minari")
    for root in (ds, ds / "steps", ds / "policies"):
        refused(capsys, export(ds, "minari", "--id", "rlu/x-v0", "--minari-dir", str(root)),
                ds.parent, "is or contains the input")  # fmt: skip
    refused(capsys, export(ds, "minari", "--minari-dir", str(ds.parent / "m")), ds.parent,
            "--id")  # fmt: skip


def test_an_existing_minari_dataset_is_left_as_it_was(ds, tmp_path, capsys):
    pytest.importorskip("minari")
    argv = export(ds, "minari", "--id", "rlu/x-v0", "--minari-dir", str(tmp_path / "m"))
    assert main(argv) == 0
    assert not [p for p in (tmp_path / "m").iterdir() if p.name.startswith(".")]  # no staging
    refused(capsys, argv, tmp_path, "already exists")


def test_an_import_into_its_own_source_is_refused(ds, tmp_path, capsys):
    assert main(export(ds, "d4rl", "-o", str(tmp_path / "x.hdf5"))) == 0
    capsys.readouterr()
    argv = ["import", str(tmp_path / "x.hdf5"), "--format", "d4rl", "--out"]
    refused(capsys, [*argv, str(ds)], tmp_path, "exists")
    refused(capsys, [*argv, ""], tmp_path, "is empty")
    assert main([*argv, str(tmp_path / "back")]) == 0
    back = open_dataset(tmp_path / "back")  # the policy came back from the sidecar
    assert (back.path / f"{POLICY}.npz").read_bytes() == (ds / f"{POLICY}.npz").read_bytes()
    assert validate(back.path).ok
