"""Random-policy scores: measurement, the file format with provenance, and the CLI."""

import json

import pytest

pytest.importorskip("dm_control")

from rlu.cli import main  # noqa: E402
from rlu.envs import scores  # noqa: E402
from rlu.types import FormatError, RluError  # noqa: E402


def test_measure_write_load_and_resume(tmp_path):
    tid = "control_suite/cartpole_swingup"
    doc = scores.measure([(tid, "none", {})], episodes=2, seed=0)
    entry = doc["scores"][tid]
    assert entry["episodes"] == 2 and entry["lengths"] == [1000, 1000]
    assert entry["mean"] == pytest.approx(sum(entry["returns"]) / 2)
    again, _ = scores.random_returns(tid, 2, seed=0)
    assert again == entry["returns"]
    prov = doc["provenance"]
    assert {"date", "code_version", "seed", "episodes", "packages"} <= set(prov)
    path = tmp_path / "rs.json"
    scores.write(doc, path)
    assert scores.random_score(tid, path=str(path)) == entry["mean"]
    with pytest.raises(RluError, match="rlu envs random-scores"):
        scores.random_score("control_suite/walker_walk", path=str(path))
    # Resuming keeps measured tasks (same numbers) and adds the new one.
    loaded = scores.load(path)
    scores.measure(
        [(tid, "none", {}), ("rwrl/cartpole_swingup", "easy", {})], 1, 0, existing=loaded
    )
    assert loaded["scores"][tid] == entry and "rwrl/cartpole_swingup@easy" in loaded["scores"]


def test_cli_writes_a_file(tmp_path, capsys):
    out = tmp_path / "scores.json"
    rc = main(["envs", "random-scores", "--task", "control_suite/cartpole_swingup",
               "--episodes", "1", "--out", str(out)])  # fmt: skip
    assert rc == 0
    doc = json.loads(out.read_text())
    assert list(doc["scores"]) == ["control_suite/cartpole_swingup"]
    assert "cartpole_swingup: mean" in capsys.readouterr().out
    assert main(["envs", "random-scores", "--task", "atari/NoSuchGame", "--out", str(out)]) == 2


def test_corrupt_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(FormatError, match="not valid JSON"):
        scores.load(bad)
    bad.write_text("{}")
    with pytest.raises(FormatError, match="rlu.random_scores"):
        scores.load(bad)


def test_shipped_scores_cover_the_suite_with_provenance():
    from rlu.domains import DOMAINS
    from rlu.tasks import list_tasks

    doc = scores.load()
    prov = doc["provenance"]
    assert prov["code_version"].startswith("rlu ") and prov["seed"] == 0
    have = doc["scores"]
    for t in list_tasks():
        if DOMAINS[t.domain].data_only:  # no env to measure a random policy in
            assert t.id not in have, t.id
            continue
        assert t.id in have, t.id
        assert have[t.id]["episodes"] >= 3 and len(have[t.id]["returns"]) == have[t.id]["episodes"]
    for t in list_tasks("rwrl"):
        assert f"{t.id}@easy" in have
    for t in list_tasks("atari"):
        assert have[t.id]["settings"].get("max_episode_steps", 27_000) == 27_000


def test_workers_and_resume_by_episode_count(tmp_path, capsys):
    pytest.importorskip("ale_py")
    jobs = [("atari/Breakout", "none", {}), ("atari/Asterix", "none", {})]
    one = scores.measure(jobs, 2, seed=0)
    two = scores.measure(jobs, 2, seed=0, workers=2)
    for key in ("atari/Breakout", "atari/Asterix"):
        # an entry is a function of (task, episodes, seed, settings): workers change nothing
        assert one["scores"][key]["returns"] == two["scores"][key]["returns"]
        e = two["scores"][key]
        assert e["seed"] == 0 and e["steps"] == sum(e["lengths"]) and e["cpu_seconds"] > 0
    run = two["provenance"]["runs"][0]
    assert sorted(run["tasks"]) == ["atari/Asterix", "atari/Breakout"] and run["workers"] == 2
    assert run["steps"] == sum(e["steps"] for e in two["scores"].values())
    # resuming with more episodes re-measures a task (its first episodes come out the same),
    # with fewer keeps it, with another seed re-measures it
    before = one["scores"]["atari/Breakout"]["returns"]
    scores.measure(jobs[:1], 3, seed=0, existing=one)
    after = one["scores"]["atari/Breakout"]
    assert after["episodes"] == 3 and after["returns"][:2] == before
    assert len(one["provenance"]["runs"]) == 2 and one["provenance"]["runs"][1]["episodes"] == 3
    scores.measure(jobs, 1, seed=0, existing=one)
    assert one["scores"]["atari/Breakout"] == after and len(one["provenance"]["runs"]) == 2
    scores.measure(jobs[1:], 2, seed=1, existing=one)
    assert one["scores"]["atari/Asterix"]["seed"] == 1
    # the CLI: progress per task, a resumed run says what it keeps, a bad --workers is an error
    out = tmp_path / "rs.json"
    argv = ["envs", "random-scores", "--task", "atari/Breakout", "--episodes", "1", "--out"]
    assert main([*argv, str(out)]) == 0
    assert "[1/1] atari/Breakout: mean" in capsys.readouterr().out
    assert main([*argv, str(out), "--resume"]) == 0
    assert "keeping 1 of 1 tasks" in capsys.readouterr().out
    with pytest.raises(SystemExit) as stop:  # refused by the parser
        main([*argv, str(out), "--workers", "0"])
    assert stop.value.code == 2 and "--workers: 0 is out of range" in capsys.readouterr().err
    with pytest.raises(RluError, match="workers=0"):
        scores.measure(jobs, 1, workers=0)


def test_random_scores_skip_the_data_only_domains(tmp_path, capsys, monkeypatch):
    """Without --task, every task with an env is measured and DMLab's (data only: no env) are
    left out, also with --domain dmlab; a data-only task named with --task gets its domain's
    refusal."""
    from rlu.domains import DOMAINS
    from rlu.tasks import list_tasks

    data_only = {t.id for t in list_tasks() if DOMAINS[t.domain].data_only}
    playable = {t.id for t in list_tasks()} - data_only
    assert any(t.startswith("dmlab/") for t in data_only) and playable
    asked: list[str] = []
    real = scores.measure

    def measure(jobs, *args, **kw):  # records the tasks instead of playing them
        if not jobs:
            return real(jobs, *args, **kw)
        asked.extend(task for task, _, _ in jobs)
        return kw["existing"]

    monkeypatch.setattr(scores, "measure", measure)
    out = str(tmp_path / "rs.json")
    argv = ["envs", "random-scores", "--episodes", "1", "--out", out]
    assert main(argv) == 0
    assert set(asked) == playable
    asked.clear()
    assert main([*argv, "--domain", "dmlab"]) == 0
    assert asked == [] and "wrote 0 tasks" in capsys.readouterr().out
    dmlab = sorted(data_only)[0]
    assert main([*argv, "--task", dmlab]) == 0 and asked == [dmlab]  # named: not skipped
    monkeypatch.undo()
    capsys.readouterr()
    assert main([*argv, "--task", dmlab]) == 2
    assert "data only" in capsys.readouterr().err
