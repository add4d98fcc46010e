"""The Atari best-behaviour reference: the shipped file and its recomputation from release files
(``rlu.evaluation.reference``, ``rlu envs best-behaviour``)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from rlu.cli import main
from rlu.data.release import families as Fm
from rlu.evaluation import reference
from rlu.evaluation.scores import load_reference_scores
from rlu.tasks import list_tasks
from rlu.types import FormatError, RluError
from tests.release.test_families import atari_episode


def test_shipped_reference_covers_every_atari_game_above_random():
    doc = reference.load()
    atari = {t.id for t in list_tasks("atari")}
    assert set(doc["scores"]) == atari and len(atari) == 46
    random = load_reference_scores("random_scores")
    for tid, entry in doc["scores"].items():
        assert entry["mean"] > random[tid], tid  # a normaliser must exceed the random score
        # five Dopamine runs per game, each with its best iteration; the reference is their mean
        assert entry["file"].startswith("baselines/atari/data/"), tid
        runs = entry["runs"]
        assert sorted(runs) == ["1", "2", "3", "4", "5"], tid
        for r in runs.values():
            assert 0 <= r["iteration"] < entry["iterations"] == 199
        bests = [r["mean"] for r in runs.values()]
        assert entry["mean"] == pytest.approx(np.mean(bests)), tid
        assert entry["runs_std"] == pytest.approx(np.std(bests, ddof=1)), tid
    prov = doc["provenance"]
    for key in ("source", "layout", "value", "agent", "statistic", "why", "caveats"):
        assert prov[key], key
    assert "github.com/google/dopamine" in prov["source"]
    assert re.search(r"commit [0-9a-f]{40}", prov["source"])
    # the numbers the report normalises with are these, on the raw score scale; Pong's five
    # runs' bests (Dopamine's baselines/atari/data/pong.json): 18.68, 17.17, 17.60, 14.76, 18.98
    best = load_reference_scores("atari_best_behaviour")
    assert best["atari/Pong"] == pytest.approx(17.437, abs=1e-3)
    assert doc["scores"]["atari/Pong"]["runs"]["1"]["mean"] == pytest.approx(18.6814, abs=1e-3)
    assert reference.best_behaviour("atari/Breakout") == best["atari/Breakout"]


def test_load_rejects_other_files(tmp_path):
    p = tmp_path / "r.json"
    p.write_text('{"scores": {}}')
    with pytest.raises(FormatError, match="format"):
        reference.load(p)
    p.write_text("{nope")
    with pytest.raises(FormatError, match="not valid JSON"):
        reference.load(p)
    p.write_text(json.dumps({"format": reference.FORMAT, "scores": {"atari/Pong": {"x": 1}}}))
    with pytest.raises(FormatError, match="numeric 'mean'"):
        reference.load(p)
    with pytest.raises(RluError, match="check the path"):
        reference.load(tmp_path / "missing.json")
    with pytest.raises(RluError, match="rlu envs best-behaviour"):
        reference.best_behaviour("atari/NoSuchGame")


def _episodes(rng, returns_by_ckpt):
    out = []
    for ckpt, returns in returns_by_ckpt:
        for ret in returns:
            ep = atari_episode(rng, 3)
            ep["checkpoint_idx"] = np.int64(ckpt)
            ep["episode_return"] = np.float32(ret)
            out.append(ep)
    return out


def _release(tmp_path):
    """Run 1: checkpoint 0 returns 2, 4 (mean 3); checkpoint 1 returns 10, 0 (mean 5, best).
    Run 2: checkpoint 0 returns 7 (best); checkpoint 1 returns 6, 6.
    The reference averages the runs' best checkpoints: (5 + 7) / 2 = 6."""
    rng = np.random.default_rng(0)
    shards = {
        "run_1-00000-of-00002": [(0, [2.0, 4.0])],
        "run_1-00001-of-00002": [(1, [10.0, 0.0])],
        "run_2-00000-of-00001": [(0, [7.0]), (1, [6.0, 6.0])],
    }
    paths = []
    for name, groups in shards.items():
        path = tmp_path / name
        Fm.write_shard(path, "atari_episodes_ordered", _episodes(rng, groups))
        paths.append(str(path))
    return paths


def test_best_behaviour_from_release_files(tmp_path):
    paths = _release(tmp_path)
    assert reference.checkpoint_returns(paths[2]) == {0: [7.0], 1: [6.0, 6.0]}
    got = reference.best_behaviour_from_release(paths)
    assert got["mean"] == pytest.approx(6.0)
    assert got["runs"]["1"]["checkpoint"] == 1 and got["runs"]["1"]["mean"] == pytest.approx(5)
    assert got["runs"]["2"]["checkpoint"] == 0 and got["runs"]["2"]["mean"] == pytest.approx(7)
    assert got["episodes"] == 7
    # one run alone is that run's best checkpoint
    assert reference.best_behaviour_from_release(paths[:2])["mean"] == pytest.approx(5.0)


def test_cli_writes_a_reference_the_report_reads(tmp_path, capsys):
    paths = _release(tmp_path)
    out = tmp_path / "best.json"
    rc = main(["envs", "best-behaviour", *paths, "--task", "atari/Pong", "--out", str(out)])
    assert rc == 0
    assert "atari/Pong: 6.00" in capsys.readouterr().out
    assert reference.best_behaviour("atari/Pong", out) == pytest.approx(6.0)
    assert load_reference_scores(str(out)) == {"atari/Pong": pytest.approx(6.0)}
    assert reference.load(out)["scores"]["atari/Pong"]["files"] == 3


def test_cli_errors(tmp_path, capsys):
    paths = _release(tmp_path)
    out = str(tmp_path / "o.json")
    bad = tmp_path / "episodes-00000-of-00001"  # no run_N in the name
    Fm.write_shard(bad, "atari_episodes_ordered", _episodes(np.random.default_rng(1), [(0, [1])]))
    assert main(["envs", "best-behaviour", str(bad), "--task", "atari/Pong", "--out", out]) == 2
    assert "no run_N" in capsys.readouterr().err
    assert main(["envs", "best-behaviour", *paths, "--out", out]) == 2  # which game?
    assert main(["envs", "best-behaviour", "--src", str(tmp_path), "--out", out]) == 2
    rc = main(["envs", "best-behaviour", "--src", str(tmp_path), "--task",
               "control_suite/cartpole_swingup", "--out", out])  # fmt: skip
    assert rc == 2 and "not an Atari task" in capsys.readouterr().err
    rc = main(["envs", "best-behaviour", "--src", str(tmp_path), "--task", "atari/Pong",
               "--out", out])  # fmt: skip
    assert rc == 2 and "rlu download atari/Pong" in capsys.readouterr().err
