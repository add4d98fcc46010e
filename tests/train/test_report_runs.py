"""rlu report of any runs (issue 37 item 1): run folders from ``rlu train``, sweeps, or a mix,
grouped by what each run recorded, with learning curves and rliable's views; refused only what
cannot be grouped, saying why. The report folder is checked before any work and every file goes
through rlu.files (issue 39): never '', an input, a folder inside or holding one, or a folder
holding anything but an earlier report of rlu's. FQE results hold null, not NaN."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from rlu.report import read_inputs, write_report
from rlu.types import RluError
from tests.fakes import train_config
from tests.train.conftest import AGENTS

ENV = "tests.train.pendulum:make_env"


@pytest.fixture(scope="module")
def hand_runs(pendulum_datasets, tmp_path_factory):
    """Three ``rlu train`` runs on test/pendulum: the first agent with seeds 0 and 1, the second
    with seed 0; each evaluated at steps 10, 20 and 30 (its learning curve)."""
    pytest.importorskip("matplotlib")
    from rlu.training.train import train

    root = tmp_path_factory.mktemp("hand_runs")
    out = {}
    for agent, seed in ((AGENTS[0], 0), (AGENTS[0], 1), (AGENTS[1], 0)):
        cfg = train_config(task="test/pendulum", agent=agent, dataset=pendulum_datasets[
            "test/pendulum"], seed=seed, steps=30, eval_every=10, eval_episodes=2, eval_envs=2,
            eval_max_steps=20, log_every=10, checkpoint_every=30, env=ENV)  # fmt: skip
        run = root / f"{agent.rsplit('.', 1)[-1]}_{seed}"
        train(cfg, run)
        out[(agent, seed)] = run
    return out


def _tree(path: Path) -> dict[str, int]:
    return {str(p): p.stat().st_mtime_ns for p in sorted(path.rglob("*")) if p.is_file()}


def test_runs_and_a_sweep_in_one_report(hand_runs, local_sweep, tmp_path):
    sweep_dir, records = local_sweep
    runs = list(hand_runs.values())
    out = tmp_path / "report"
    paths = write_report([*runs, sweep_dir], out)
    rep = json.loads((out / "report.json").read_text())
    assert rep["written_by"] == "rlu report" and rep["inputs"] == [
        str(p) for p in (*runs, sweep_dir)
    ]
    dom = rep["domains"]["other"]
    assert dom["panels"] == ["online", "aggregates", "dataset_p90", "task_bars", "curves",
                             "profiles", "improvement"]  # fmt: skip
    recs, _, _ = read_inputs([*runs, sweep_dir])
    assert len(recs) == len(records) + 3
    # the hand runs are their own configuration ("default": no overrides) beside the sweep's
    hand = [r for r in recs if r["config"] == "default"]
    assert sorted((r["agent"], r["seed"]) for r in hand) == sorted(hand_runs)
    # the learning curves: each run's eval.jsonl, seeds as lines, their mean at shared steps
    (pend,) = [t for t in dom["curves"]["tasks"] if t["task"] == "test/pendulum"]
    for agent, c in pend["agents"].items():
        if c["config"] == "default":
            run_dirs = [hand_runs[(agent, s)] for s in (0, 1) if (agent, s) in hand_runs]
        else:
            key = ("test/pendulum", agent, c["config"])
            run_dirs = [
                Path(r["run"]) for r in records if (r["task"], r["agent"], r["config"]) == key
            ]
        logs = [[json.loads(x) for x in (d / "eval.jsonl").read_text().splitlines()]
                for d in run_dirs]  # fmt: skip
        assert [s["means"] for s in c["seeds"]] == [[e["mean"] for e in log] for log in logs]
        assert c["steps"] == [e["step"] for e in logs[0]]
        expect = np.array([[e["mean"] for e in log] for log in logs])
        assert c["mean"] == pytest.approx(expect.mean(0))
        assert c["std"] == (pytest.approx(expect.std(0, ddof=1)) if len(logs) > 1 else None)
    # rliable's views: a profile per agent, a probability of improvement per pair of agents
    prof = dom["profiles"]["splits"]["online"]
    assert sorted(prof["agents"]) == sorted(AGENTS) and len(prof["tau"]) == 101
    (pair,) = dom["improvement"]["splits"]["online"]["pairs"]
    assert {pair["x"], pair["y"]} == set(AGENTS) and 0.0 <= pair["probability"] <= 1.0
    names = sorted(p.name for p in paths if p.suffix == ".png")
    assert names == ["other_curves.png", "other_improvement.png", "other_profiles.png",
                     "other_tasks.png"]  # fmt: skip
    md = (out / "report.md").read_text()
    for title in (
        "Learning curves: evaluation return against learner steps",
        "Performance profiles (rliable's",
        "Probability of improvement (rliable's",
    ):
        assert title in md  # fmt: skip


def test_a_run_given_twice_counts_once_and_what_cannot_be_grouped_is_refused(
    hand_runs, local_sweep, tmp_path
):
    sweep_dir, records = local_sweep
    run = hand_runs[(AGENTS[0], 0)]
    one_of_the_sweep = Path(records[0]["run"])
    recs, _, _ = read_inputs([run, run, sweep_dir, one_of_the_sweep])
    assert len(recs) == len(records) + 1
    with pytest.raises(RluError, match="neither a run folder .* nor a sweep folder"):
        read_inputs([run, tmp_path])
    with pytest.raises(RluError, match="does not exist"):
        read_inputs([tmp_path / "nothing"])
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    with pytest.raises(RluError, match=r"is test/pendulum .* default seed 0, and so is .* same"):
        read_inputs([run, copy])
    (copy / "result.json").unlink()
    with pytest.raises(RluError, match="result.json is missing: the run is still training"):
        read_inputs([copy])
    # the same configuration and seed trained otherwise: told apart by what differs
    shutil.rmtree(copy)
    shutil.copytree(run, copy)
    result = json.loads((copy / "result.json").read_text())
    (copy / "result.json").write_text(json.dumps({**result, "preset": "paper"}))
    recs, _, _ = read_inputs([run, copy])
    assert sorted(r["config"] for r in recs) == ["default (preset paper)", "default (preset small)"]


def test_the_cli_reports_run_folders(hand_runs, tmp_path, capsys):
    from rlu.cli import main

    runs = [str(p) for p in hand_runs.values()]
    assert main(["report", *runs, "--out", str(tmp_path / "r")]) == 0
    assert f"wrote {tmp_path / 'r' / 'report.md'}" in capsys.readouterr().out
    assert main(["report", *runs]) == 2  # several folders: --out
    assert "pass --out" in capsys.readouterr().err
    # the library's one call is the command's: rlu.report(paths), also once the report's package
    # (rlu/report/, which the import binds to the name rlu.report) is imported
    import rlu
    from rlu.report import report

    assert rlu.report.report is report and callable(rlu.report)
    written = rlu.report(runs, tmp_path / "r2", figures=False)
    assert sorted(p.name for p in written) == ["report.html", "report.json", "report.md"]
    # one run folder: its own report subfolder by default
    assert main(["report", runs[0]]) == 0
    assert (Path(runs[0]) / "report" / "report.html").is_file()
    shutil.rmtree(Path(runs[0]) / "report")


# --- the report folder (issue 39) --------------------------------------------------------------
def test_report_folders_that_are_refused_before_any_work(hand_runs, local_sweep, tmp_path,
                                                           pendulum_datasets):  # fmt: skip
    from rlu.cli import main

    sweep_dir, _ = local_sweep
    run = hand_runs[(AGENTS[0], 0)]
    data = Path(pendulum_datasets["test/pendulum"])
    other_data = tmp_path / "dataset"  # an rlu dataset, not an input
    shutil.copytree(data, other_data)
    unrelated = tmp_path / "notes"
    unrelated.mkdir()
    (unrelated / "report.md").write_text("my own notes\n")
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "report.json").write_text('{"mine": true}\n')
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "somewhere", target_is_directory=True)
    cases = {
        "": "--out is empty",
        str(sweep_dir): "is or contains the input",
        str(run / "checkpoints"): "is or contains the input",
        str(run): "is or contains the input",
        str(data): "is or contains the input",
        str(other_data): "is not an rlu report folder",
        str(unrelated): "is not an rlu report folder",
        str(foreign): "holds a report.json that rlu report did not write",
        str(link): "exists and is not a folder",
    }
    before = {p: _tree(p) for p in (sweep_dir, run, data, other_data, unrelated, foreign)}
    for out, why in cases.items():
        with pytest.raises(RluError, match=why):
            write_report([run, sweep_dir], out)
    # the command line says the same and computes nothing first (FQE would write fqe.json)
    assert main(["report", str(sweep_dir), "--fqe", "--fqe-steps", "5", "--out",
                 str(sweep_dir)]) == 2  # fmt: skip
    assert not (sweep_dir / "fqe.json").exists()
    assert {p: _tree(p) for p in before} == before
    assert not (tmp_path / "somewhere").exists()
    assert (unrelated / "report.md").read_text() == "my own notes\n"


def test_an_earlier_report_is_replaced_through_checked_files(hand_runs, tmp_path):
    pytest.importorskip("matplotlib")
    runs = list(hand_runs.values())
    out = tmp_path / "r"
    write_report(runs, out)
    assert (out / "figures" / "other_curves.png").is_file()
    # an earlier report of rlu's is replaced; a figure it drew that this one does not is gone,
    # a file it did not list is kept
    (out / "figures" / "other_iqn_tau.png").write_bytes(b"x")
    data = json.loads((out / "report.json").read_text())
    (out / "report.json").write_text(json.dumps({**data, "figures": [*data["figures"],
                                                 "figures/other_iqn_tau.png"]}))  # fmt: skip
    (out / "figures" / "mine.png").write_bytes(b"mine")
    write_report(runs, out)
    assert not (out / "figures" / "other_iqn_tau.png").exists()
    assert (out / "figures" / "mine.png").read_bytes() == b"mine"
    assert not [p for p in out.rglob("*") if ".tmp" in p.name]  # no temporary left
    # a link planted where the report writes is refused, and its target untouched
    target = tmp_path / "precious.md"
    target.write_text("precious\n")
    (out / "report.md").unlink()
    (out / "report.md").symlink_to(target)
    with pytest.raises(RluError, match="is a symbolic link"):
        write_report(runs, out)
    assert target.read_text() == "precious\n"
    (out / "report.md").unlink()
    png = out / "figures" / "other_tasks.png"
    png.unlink()
    os.link(target, png)  # a hard link planted at a figure's path
    with pytest.raises(RluError, match="has another hard link"):
        write_report(runs, out)
    assert target.read_text() == "precious\n"


# --- FQE results (issue 39) -------------------------------------------------------------------
def test_fqe_results_hold_null_and_the_report_reads_them_back(local_sweep, tmp_path):
    """One configuration per (task, agent): FQE has no rank correlation to give. fqe.json holds
    null there (JSON has no NaN), the report reads it back and says why; an fqe.json written
    before that, with NaN, is read as null instead of refused as not JSON."""
    pytest.importorskip("jinja2")
    from rlu.evaluation.fqe import FQEConfig
    from rlu.training.restore import fqe_selection

    src, _ = local_sweep
    sweep_dir = tmp_path / "sweep"
    shutil.copytree(src, sweep_dir)
    lines = (sweep_dir / "results.jsonl").read_text().splitlines()
    keep = [x for x in lines if json.loads(x)["config"] == "learning_rate=0.01"]
    (sweep_dir / "results.jsonl").write_text("\n".join(keep) + "\n")
    fqe_selection(sweep_dir, FQEConfig(steps=5, hidden=(8,), batch_size=32), quiet=True)
    text = (sweep_dir / "fqe.json").read_text()
    assert "NaN" not in text
    saved = json.loads(text)
    assert saved["selections"] and all(s["spearman"] is None for s in saved["selections"])
    write_report(sweep_dir, tmp_path / "r", figures=False)
    md = (tmp_path / "r" / "report.md").read_text()
    assert md.count("- (one config)") == len(saved["selections"])
    old = text.replace('"spearman": null', '"spearman": NaN')
    assert "NaN" in old
    (sweep_dir / "fqe.json").write_text(old)
    write_report(sweep_dir, tmp_path / "r", figures=False)
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    assert all(x["spearman"] is None for x in rep["domains"]["other"]["fqe"])
    assert not any(
        isinstance(v, float) and math.isnan(v) for v in rep["domains"]["other"]["fqe"][0].values()
    )


# --- the whole loop, for real, in a browser ------------------------------------------------------
@pytest.mark.slow
def test_report_of_train_runs_and_a_sweep_on_the_bundled_data_in_chromium(tmp_path):
    """Three ``rlu train`` runs (BC seeds 0 and 1, D4PG seed 0; small presets, 200 learner
    steps on the bundled cartpole swingup data, evaluated in dm_control) and one sweep (IQL,
    seeds 0 and 1) in one report: its Markdown, its figures (learning curves, a performance
    profile, the probability of improvement, each labelled) and report.html as headless
    chromium draws it."""
    pytest.importorskip("dm_control")
    pytest.importorskip("matplotlib")
    pytest.importorskip("PIL")
    from rlu.data.bundled import bundled_dataset_path
    from rlu.report import report
    from rlu.training.sweep import sweep
    from rlu.training.train import train
    from rlu.workers import Backend
    from tests.evaluation.test_report import screenshot
    from tests.fakes import sweep_config

    task = "control_suite/cartpole_swingup"
    data = str(bundled_dataset_path(task))
    settings = dict(steps=200, eval_every=100, eval_episodes=1, eval_envs=1, eval_max_steps=100,
                    checkpoint_every=200, log_every=100)  # fmt: skip
    runs = []
    for agent, seed in (("bc", 0), ("bc", 1), ("d4pg", 0)):
        runs.append(tmp_path / f"{agent}_{seed}")
        train(train_config(task=task, agent=agent, dataset=data, seed=seed, **settings), runs[-1])
    cfg = sweep_config(tasks=(task,), agents=("iql",), datasets={task: data}, seeds=(0, 1),
                       max_configs=1, **settings)  # fmt: skip
    sweep(cfg, tmp_path / "sweep", Backend("local", 1))
    out = tmp_path / "report"
    paths = report([*runs, tmp_path / "sweep"], out)
    names = sorted(p.name for p in paths)
    assert names == ["control_suite_curves.png", "control_suite_improvement.png",
                     "control_suite_profiles.png", "control_suite_tasks.png", "report.html",
                     "report.json", "report.md"]  # fmt: skip
    dom = json.loads((out / "report.json").read_text())["domains"]["control_suite"]
    curves = {a: c for t in dom["curves"]["tasks"] for a, c in t["agents"].items()}
    assert {a: c["n_seeds"] for a, c in curves.items()} == {"bc": 2, "d4pg": 1, "iql": 2}
    assert all(c["steps"] == [100, 200] for c in curves.values())
    md = (out / "report.md").read_text()
    for words in (
        "Learning curves: evaluation return against learner steps",
        "Performance profiles (rliable's",
        "Probability of improvement (rliable's",
        "(1 seed) (not comparable: preset, budget, data, episodes, seeds)",
        "the paper states no budget",
    ):
        assert words in md, words  # fmt: skip
    for name in ("curves", "profiles", "improvement", "tasks"):
        assert f"(figures/control_suite_{name}.png)" in md
    from PIL import Image

    for name in ("curves", "profiles", "improvement"):
        png = out / "figures" / f"control_suite_{name}.png"
        assert Image.open(png).size[0] >= 600 and png.stat().st_size > 20_000, name
    img = screenshot(out / "report.html", tmp_path / "shot.png", tmp_path / "profile",
                     size=(1200, 6000))  # fmt: skip
    ink = np.any(img < 200, axis=2).mean()
    assert 0.02 < ink < 0.6, f"{ink:.3f} of the page is ink: blank or unstyled"
    # the figures are on screen: matplotlib's first three colours (bc, d4pg, iql) fill their
    # bars and curves
    colours = ((31, 119, 180), (255, 127, 14), (44, 160, 44))
    drawn = [np.all(np.abs(img.astype(int) - c) <= 8, axis=2).sum() for c in colours]
    assert min(drawn) > 1000, drawn
    for png in (out / "figures").iterdir():
        png.unlink()
    img2 = screenshot(out / "report.html", tmp_path / "shot2.png", tmp_path / "p2",
                      size=(1200, 6000))  # fmt: skip
    assert np.all(np.abs(img2.astype(int) - colours[0]) <= 8, axis=2).sum() < 100
