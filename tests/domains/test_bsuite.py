"""bsuite as a domain: its tasks in ``rlu list``, a TF-written shard converted, DQN trained on it
for 5 steps and evaluated in bsuite's env from the command line (the env part skips without the
``bsuite`` extra)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from rlu.cli import main

SHARD = Path(__file__).resolve().parents[1] / "fixtures" / "release" / "bsuite" / "catch"
SHARD = SHARD / "0_0.1" / "0_full-00000-of-00001"


def test_bsuite_tasks_are_listed(capsys):
    assert main(["list", "--domain", "bsuite"]) == 0
    out = capsys.readouterr().out
    for name in ("bsuite/catch", "bsuite/cartpole", "bsuite/mountain_car"):
        assert name in out


def test_bsuite_objects_are_the_releases():
    from rlu.data.release import catalog

    sel = catalog.select("bsuite/catch", run="0.1/0")
    assert sel.objects == ("bsuite/catch/0_0.1/0_full-00000-of-00001",)
    assert len(catalog.select("bsuite/mountain_car").release.shards) == 30  # 6 noises x 5 runs
    with pytest.raises(Exception, match="give --run NOISE/RUN"):
        catalog.select("bsuite/catch", run="0.7/0")


@pytest.fixture
def converted(tmp_path):
    out = tmp_path / "data"
    args = [
        "convert",
        str(SHARD),
        "--family",
        "bsuite",
        "--task",
        "bsuite/catch",
        "--out",
        str(out),
    ]
    assert main(args) == 0
    return out


def test_a_tf_written_bsuite_shard_converts(converted):
    from rlu.data.store import open_dataset

    ds = open_dataset(converted)
    assert ds.schema.task_id == "bsuite/catch" and tuple(ds.schema.observation.shape) == (50,)
    exp = np.load(f"{SHARD}.npz")
    assert ds.num_steps == exp["step_type"].size


def test_dqn_trains_5_steps_and_evaluates_in_bsuite(converted, tmp_path):
    pytest.importorskip("torch")
    if importlib.util.find_spec("bsuite") is None:
        pytest.skip("the bsuite extra is not installed (pip install 'rlu[bsuite]')")
    run = tmp_path / "run"
    argv = ["train", "--task", "bsuite/catch", "--agent", "dqn", "--dataset", str(converted),
            "--out", str(run), "--steps", "5", "--eval-every", "0", "--eval-episodes", "2",
            "--eval-envs", "1", "--device", "cpu", "--quiet", "atari.batch_size=4"]  # fmt: skip
    assert main(argv) == 0
    result = json.loads((run / "result.json").read_text())
    assert result["steps"] == 5 and result["final_eval"]["lengths"] == [9, 9]
    assert all(r in (-1.0, 1.0) for r in result["final_eval"]["returns"])  # catch pays +-1
    assert main(["evaluate", str(run), "--eval-episodes", "2"]) == 0
