"""The bundled default dataset: valid, within budget, and made by the command it records."""

from __future__ import annotations

import shlex

import pytest

from rlu.data import open_dataset
from rlu.data.bundled import bundled_dataset, bundled_tasks
from rlu.data.validate import validate

BUNDLED_TASK = "control_suite/cartpole_swingup"


def test_bundled_dataset_is_valid_and_small():
    assert bundled_tasks() == [BUNDLED_TASK]
    path = bundled_dataset()
    assert path == bundled_dataset(BUNDLED_TASK)
    report = validate(path)
    assert report.ok, report.problems
    ds = open_dataset(path)
    assert ds.schema.task_id == BUNDLED_TASK
    assert ds.info()["returns"]["episodes"] == 40  # the paper's cartpole swingup count
    size = sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    assert size <= 5 * 2**20
    prov = ds.manifest["provenance"]
    assert prov["command"].startswith(f"rlu generate {BUNDLED_TASK} --scale laptop")
    assert prov["settings"]["seed"] == 0 and prov["selection"]["kept"] == 40
    runs = {ds.segment(i).metadata["run"] for i in range(len(ds))}
    assert runs == {0, 1, 2}


def test_a_task_without_a_bundled_dataset_is_a_clear_error():
    from rlu.types import RluError

    with pytest.raises(
        RluError, match=f"no bundled dataset for 'atari/Pong'.*ships {BUNDLED_TASK}"
    ):
        bundled_dataset("atari/Pong")


@pytest.mark.slow
@pytest.mark.long  # outside CI: RLU_SLOW=2
def test_bundled_dataset_is_reproduced_by_its_recorded_command(tmp_path):
    """Minutes: re-runs the recorded command (3 D4PG runs at the laptop scale)."""
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    from rlu.cli import main

    path = bundled_dataset()
    argv = shlex.split(open_dataset(path).manifest["provenance"]["command"])
    assert argv[:2] == ["rlu", "generate"] and argv[-2:] == ["--out", "DIR"]
    out = tmp_path / "again"
    assert main([*argv[1:-1], str(out), "--no-progress"]) == 0
    for p in sorted(q for q in path.rglob("*") if q.is_file()):
        assert (out / p.relative_to(path)).read_bytes() == p.read_bytes(), p
