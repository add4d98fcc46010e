"""rlu report: the tables' numbers against the run files, the paper's numbers beside ours, Atari
normalised aggregates, and the files (Markdown, HTML, PNG) it writes."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from rlu.report import build_report, paper_entry, write_report


def test_report_tables_match_the_run_files(local_sweep, tmp_path):
    pytest.importorskip("matplotlib")
    sweep_dir, _ = local_sweep
    paths = write_report(sweep_dir, tmp_path / "report")
    names = sorted(p.name for p in paths)
    assert names == ["other_curves.png", "other_improvement.png", "other_profiles.png",
                     "other_tasks.png", "report.html", "report.json", "report.md"]  # fmt: skip
    rep = json.loads((tmp_path / "report" / "report.json").read_text())
    md = (tmp_path / "report" / "report.md").read_text()

    # recompute every cell from the run folders' eval.jsonl: per (task, agent) the config with
    # the best mean over seeds of the final evaluation's mean return
    finals: dict = defaultdict(dict)
    for run in Path(sweep_dir).glob("*/*/*/seed_*"):
        last = json.loads((run / "eval.jsonl").read_text().splitlines()[-1])
        task_dir, agent_dir, cfg_dir = run.parts[-4:-1]
        finals[(task_dir, agent_dir)].setdefault(cfg_dir, []).append(np.mean(last["returns"]))
    dom = rep["domains"]["other"]
    assert len(dom["online"]["rows"]) == 2
    for row in dom["online"]["rows"]:
        best = max(row["cells"].values(), key=lambda c: c["mean"])
        for agent, cell in row["cells"].items():
            by_cfg = finals[(row["task"].replace("/", "__"), agent)]
            means = {c: np.mean(v) for c, v in by_cfg.items()}
            chosen = max(means, key=means.get)
            assert len(by_cfg[chosen]) == 2  # two seeds
            assert cell["mean"] == pytest.approx(np.mean(by_cfg[chosen]), rel=1e-12)
            assert cell["std"] == pytest.approx(np.std(by_cfg[chosen], ddof=1), rel=1e-12)
            text = f"{cell['mean']:.1f} ± {cell['std']:.1f}"
            bold = cell["mean"] + cell["std"] >= best["mean"] - best["std"]
            assert cell["bold"] == bold
            assert (f"**{text}**" if bold else f"| {text} |") in md
    # the p90 line is the dataset's 90th-percentile return
    from rlu.data import open_dataset

    for task, p90 in dom["dataset_p90"].items():
        ds_path = json.loads((Path(sweep_dir) / "sweep.json").read_text())["datasets"][task]
        assert p90 == pytest.approx(np.percentile(open_dataset(ds_path).episode_returns(), 90))
    agg = dom["aggregates"]
    assert agg["statistic"] == "mean" and "offline" not in agg  # test tasks: online selection
    for agent in dom["agents"]:
        cells = [row["cells"][agent]["mean"] for row in dom["online"]["rows"]]
        e = agg["online"]["agents"][agent]
        assert e["mean"] == pytest.approx(np.mean(cells))
        lo, hi = e["interval_25_75"]
        assert lo <= e["mean"] <= hi or np.isclose(lo, hi)
    # the learning curves are each run's eval.jsonl, the mean over seeds at the shared steps
    for t in dom["curves"]["tasks"]:
        for agent, c in t["agents"].items():
            runs = sorted(Path(sweep_dir).glob(f"{t['task'].replace('/', '__')}/{agent}/"
                                               f"{c['config']}/seed_*"))  # fmt: skip
            logs = [[json.loads(x) for x in (r / "eval.jsonl").read_text().splitlines()]
                    for r in runs]  # fmt: skip
            assert [s["means"] for s in c["seeds"]] == [[e["mean"] for e in log] for log in logs]
            assert c["mean"] == pytest.approx(np.mean([[e["mean"] for e in log] for log in logs],
                                                      axis=0))  # fmt: skip
    html = (tmp_path / "report" / "report.html").read_text()
    # what produced the numbers, the paper's conditions (none here: test tasks), the online
    # table, the aggregates, the p90 lines, the curves, the profiles, the improvement
    assert html.count("<table>") == 7 and "<b>" in html and "other_tasks.png" in html
    for task, p90 in dom["dataset_p90"].items():
        assert f"| {task} | online | {p90:.1f} |" in md
    # a cell far below the best is not bold; one overlapping it is
    rows = [{"task": "t", "agent": a, "config": "c", "seed": s, "score": v}
            for a, vals in (("x", [10.0, 12.0]), ("y", [11.0, 13.0]), ("z", [0.0, 1.0]))
            for s, v in enumerate(vals)]  # fmt: skip
    cells = build_report(rows, reps=100)["domains"]["other"]["online"]["rows"][0]["cells"]
    assert [cells[a]["bold"] for a in "xyz"] == [True, True, False]
    png = (tmp_path / "report" / "figures" / "other_tasks.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000


def test_paper_numbers_beside_ours():
    assert paper_entry("control_suite/cartpole_swingup", "bc") == {
        "mean": 386.0,
        "std": 6.0,
        "bold": False,
    }
    assert paper_entry("locomotion/rodent_two_touch", "rabm")["mean"] == 599.0
    assert paper_entry("atari/Pong", "iqn")["mean"] == 19.2
    assert paper_entry("test/pendulum", "bc") is None
    assert paper_entry("control_suite/cartpole_swingup", "tests.train.fake_agent") is None
    rep = build_report(
        [
            {
                "task": "control_suite/cartpole_swingup",
                "agent": "bc",
                "config": "a",
                "seed": s,
                "score": v,
            }
            for s, v in enumerate([300.0, 310.0])
        ],  # fmt: skip
        reps=200,
    )
    row = rep["domains"]["control_suite"]["online"]["rows"][0]
    assert row["paper"]["bc"]["mean"] == 386.0 and row["cells"]["bc"]["mean"] == 305.0


def test_paper_number_stays_where_rlu_has_no_cell():
    """A sweep still running, or an agent not run on every task: the paper's column keeps its
    number, and the figure its diamond."""
    from rlu.report import render

    recs = [
        {"task": t, "agent": a, "config": "c", "seed": 0, "score": v}
        for t, a, v in [("control_suite/cartpole_swingup", "bc", 300.0),
                        ("control_suite/walker_stand", "bc", 200.0),
                        ("control_suite/walker_stand", "d4pg", 800.0)]
    ]  # fmt: skip
    rep = build_report(recs, reps=50)
    row = rep["domains"]["control_suite"]["online"]["rows"][0]
    assert row["task"] == "control_suite/cartpole_swingup" and sorted(row["cells"]) == ["bc"]
    assert row["paper"]["d4pg"] == paper_entry("control_suite/cartpole_swingup", "d4pg")
    md = render.render("report.md.j2", "t", render.sections(rep, None))
    line = next(x for x in md.splitlines() if x.startswith("| control_suite/cartpole_swingup"))
    cols = [c.strip() for c in line.strip("|").split("|")]
    # task, bc, bc (paper), d4pg (empty: not run), d4pg (paper)
    label = "(1 seed) (not comparable: preset, budget, data, episodes, seeds)"
    assert cols[1:] == [f"**300.0 {label}**", "386.0 ± 6.0", "", "856.0 ± 13.0"], cols


def test_iqm_says_how_many_seeds_and_claims_no_interval_from_one():
    """A partial sweep: the IQM is over the seeds every task has; with one seed in common the
    bootstrap has nothing to resample, so no interval is printed (it would be [x, x])."""
    from rlu.report import render

    cp, ws = "control_suite/cartpole_swingup", "control_suite/walker_stand"
    scores = {(cp, 0): 400.0, (cp, 1): 500.0, (ws, 0): 800.0}
    recs = [{"task": t, "agent": "bcq", "config": "c", "seed": s, "score": v}
            for (t, s), v in scores.items()]  # fmt: skip
    agg = build_report(recs, reps=50)["domains"]["control_suite"]["aggregates"]
    agg = agg["online"]["agents"]["bcq"]
    assert agg["iqm_seeds"] == 1 and agg["iqm_ci95"] is None
    assert agg["iqm"] == pytest.approx(600.0)  # seed 0 on both tasks, nothing trimmed
    rep = build_report(recs, reps=50)
    md = render.render("report.md.j2", "t", render.sections(rep, None))
    line = next(
        x for x in md.splitlines() if x.startswith("| online policy selection") and "| bcq" in x
    )
    assert [c.strip() for c in line.strip("|").split("|")][5:] == ["600.0 (1 seed)", ""]
    # with the second seed on walker stand, both seeds count and the interval is real
    recs.append({"task": ws, "agent": "bcq", "config": "c", "seed": 1, "score": 900.0})
    agg = build_report(recs, reps=200)["domains"]["control_suite"]["aggregates"]
    agg = agg["online"]["agents"]["bcq"]
    assert agg["iqm_seeds"] == 2
    lo, hi = agg["iqm_ci95"]
    assert lo < agg["iqm"] < hi


def test_atari_normalised_median_and_naive_offline_selection():
    random = {"Pong": -20.0, "Breakout": 0.0, "Zaxxon": 0.0}
    best = {"Pong": 20.0, "Breakout": 100.0, "Zaxxon": 1000.0}
    recs = []
    # online game Zaxxon: config "a" 500 (50 %), config "b" 100 (10 %)
    # offline games Pong and Breakout run with both configs
    table = {
        ("atari/Zaxxon", "a"): 500.0,
        ("atari/Zaxxon", "b"): 100.0,
        ("atari/Pong", "a"): 0.0,  # 50 %
        ("atari/Pong", "b"): 20.0,
        ("atari/Breakout", "a"): 30.0,  # 30 %
        ("atari/Breakout", "b"): 90.0,
    }
    for (task, cfg), v in table.items():
        for seed in (0, 1):
            recs.append({"task": task, "agent": "dqn", "config": cfg, "seed": seed, "score": v})
    # random scores keyed by task id (random_scores.json), best behaviour by game name
    random = {f"atari/{g}": v for g, v in random.items()}
    rep = build_report(recs, random_scores=random, best_behaviour=best, reps=500)
    dom = rep["domains"]["atari"]
    assert dom["normalised"]
    assert dom["offline_naive"]["chosen"] == {"dqn": "a"}
    off = {r["task"]: r["cells"]["dqn"]["mean"] for r in dom["offline_naive"]["rows"]}
    assert off == {"atari/Breakout": 30.0, "atari/Pong": 0.0}
    # each split under its own protocol, never mixed: online selection on the tuning game
    # Zaxxon (a, 50 %); naive selection (a) on the held-out games Pong 50 %, Breakout 30 %. The
    # old mixed aggregate, online selection over every game (Zaxxon a 50, Pong b 100, Breakout
    # b 90), gave a median of 90.
    agg = dom["aggregates"]
    assert agg["online"]["tasks"] == ["atari/Zaxxon"] and agg["online"]["agents"]["dqn"][
        "median"
    ] == pytest.approx(50.0)
    off = agg["offline"]
    assert off["chosen"] == {"dqn": "a"} and off["agents"]["dqn"]["median"] == pytest.approx(40.0)
    # IQM of the 4 (seed, game) values 30 30 50 50: cut 1 of 4 at each end -> mean(30, 50)
    assert off["agents"]["dqn"]["iqm"] == pytest.approx(40.0)
    # without reference scores for every game, no normalised aggregates are claimed
    rep = build_report(recs, random_scores={}, best_behaviour=best, reps=100)
    assert "aggregates" not in rep["domains"]["atari"]


def test_fqe_selection_over_a_sweep(local_sweep, tmp_path):
    import shutil

    from rlu.evaluation.fqe import FQEConfig
    from rlu.training.restore import fqe_selection

    sweep_dir = tmp_path / "sweep"
    shutil.copytree(local_sweep[0], sweep_dir)  # fqe.json must not leak into the shared sweep
    out = fqe_selection(sweep_dir, FQEConfig(steps=30, hidden=(16,), batch_size=64))
    records = [json.loads(x) for x in (sweep_dir / "results.jsonl").read_text().splitlines()]
    assert len(out["selections"]) == 4  # (task, agent) pairs
    for sel in out["selections"]:
        assert len(sel["estimates"]) == 2 and all(np.isfinite(list(sel["estimates"].values())))
        for cfg, true in sel["true_returns"].items():
            scores = [
                r["score"]
                for r in records
                if (r["task"], r["agent"], r["config"]) == (sel["task"], sel["agent"], cfg)
            ]
            assert true == pytest.approx(np.mean(scores))
        assert sel["chosen"] == max(sel["estimates"], key=sel["estimates"].get)
        best = max(sel["true_returns"].values())
        assert sel["regret_at_1"] == pytest.approx(best - sel["true_returns"][sel["chosen"]])
        assert sel["spearman"] in (-1.0, 1.0)  # two candidates
    write_report(sweep_dir, tmp_path / "report", figures=False)
    md = (tmp_path / "report" / "report.md").read_text()
    assert "Offline policy selection by FQE" in md and md.count("| test/pendulum") >= 4


def _episodes_dataset(path, returns_by_checkpoint):
    from rlu.data.store import DatasetWriter, Schema
    from rlu.segments import make_episode
    from rlu.types import ArraySpec, DiscreteSpec

    schema = Schema(ArraySpec((2,), "float32"), DiscreteSpec((), "int64", 3))
    with DatasetWriter(path, schema, {"source": "test"}) as w:
        i = 0
        for ckpt, rets in returns_by_checkpoint.items():
            for ret in rets:
                w.append(
                    make_episode(
                        np.zeros((2, 2), np.float32),
                        np.zeros(1, np.int64),
                        np.array([ret], np.float32),
                        terminal=True,
                        metadata={"episode_id": i, "run": 1, "checkpoint": ckpt},
                    )
                )
                i += 1
    return str(path)


def test_atari_is_not_normalised_from_the_sweeps_datasets(tmp_path):
    """Issue 18: no fallback estimates a game's best-behaviour score from the sweep's data; a
    game missing from the references leaves the domain's scores raw."""
    datasets = {
        "atari/Pong": _episodes_dataset(tmp_path / "pong", {0: [-20.0, -10.0], 1: [0.0, 20.0]}),
        "atari/Breakout": _episodes_dataset(tmp_path / "brk", {0: [150.0, 250.0], 1: [10.0]}),
    }
    recs = [
        {"task": t, "agent": "rem", "config": "c", "seed": s, "score": v}
        for t, v in (("atari/Pong", -5.0), ("atari/Breakout", 100.0))
        for s in (0, 1)
    ]
    rep = build_report(
        recs, datasets, random_scores={"Pong": -20.0, "Breakout": 0.0}, best_behaviour={},
        reps=200,
    )  # fmt: skip
    dom = rep["domains"]["atari"]
    assert dom["normalised"] is False and "reference_scores" not in dom
    assert "aggregates" not in dom
    # the dataset's p90 line: Pong returns -20 -10 0 20 -> 90th percentile 14
    assert dom["dataset_p90"]["atari/Pong"] == pytest.approx(14.0)
