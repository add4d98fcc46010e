"""The paper's figures in rlu report (issue 18 item 4): per-task bars under each task's
protocol, the Atari median figure's two halves, the per-game normalised improvement, the IQN tau
and BCQ threshold sensitivity; each beside the paper's numbers, each left out with a reason when
the sweep has no data for it; several sweep folders in one report; and (slow) ``rlu report`` over
real sweeps that trained and evaluated every agent in the real envs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rlu.report import build_report, load_paper_results, write_report
from rlu.types import RluError

TUNING = ["atari/BeamRider", "atari/DemonAttack", "atari/Zaxxon"]
HELD_OUT = ["atari/Pong", "atari/Breakout"]
# random 0 and best behaviour 100 for every game: a raw score is its normalised score
REFS = {g: 0.0 for g in TUNING + HELD_OUT}, {g: 100.0 for g in TUNING + HELD_OUT}


def rec(task, agent, config, seed, score, overrides=None):
    r = {"task": task, "agent": agent, "config": config, "seed": seed, "score": float(score),
         "run": f"{task}/{agent}/{config}/seed_{seed}"}  # fmt: skip
    if overrides is not None:
        r["overrides"] = overrides
    return r


def dqn_records():
    # (task, config) -> scores over seeds 0 and 1
    table = {
        ("atari/BeamRider", "a"): [40, 60],  # 50
        ("atari/BeamRider", "b"): [10, 10],  # 10
        ("atari/DemonAttack", "a"): [70, 70],  # 70
        ("atari/DemonAttack", "b"): [90, 110],  # 100
        ("atari/Zaxxon", "a"): [20, 40],  # 30
        ("atari/Zaxxon", "b"): [0, 20],  # 10
        ("atari/Pong", "a"): [80, 100],  # 90
        ("atari/Pong", "b"): [200, 200],  # better, but naive selection picks a
        ("atari/Breakout", "a"): [0, 10],  # 5
        ("atari/Breakout", "b"): [300, 300],
    }
    return [rec(t, "dqn", c, s, v) for (t, c), vals in table.items() for s, v in enumerate(vals)]


def paper_raw(game, agent):
    return load_paper_results()["atari"][game][agent]["mean"]


def test_atari_median_halves_by_hand(tmp_path):
    rep = build_report(dqn_records(), random_scores=REFS[0], best_behaviour=REFS[1], reps=500)
    dom = rep["domains"]["atari"]
    med = dom["atari_median"]
    on, off = med["online"], med["offline"]
    # online selection per tuning game: BeamRider a 50, DemonAttack b 100, Zaxxon a 30
    assert on["agents"]["dqn"]["median"] == pytest.approx(50.0)
    assert on["agents"]["dqn"]["configs"] == {
        "atari/BeamRider": "a",
        "atari/DemonAttack": "b",
        "atari/Zaxxon": "a",
    }
    assert (on["agents"]["dqn"]["games"], on["of"]) == (3, 9)
    lo, hi = on["agents"]["dqn"]["interval_25_75"]
    assert 30.0 <= lo <= 50.0 <= hi <= 100.0
    # naive: a's median over the tuning games is 50 (50 70 30), b's 10 (10 100 10) -> a on the
    # held-out games: Pong 90, Breakout 5 -> 47.5, though b is better on both
    assert off["chosen"] == {"dqn": "a"}
    assert off["agents"]["dqn"]["median"] == pytest.approx(47.5)
    assert (off["agents"]["dqn"]["games"], off["of"]) == (2, 37)
    # the paper's table normalised with the same references (here: its raw scores) over the
    # same games; over all 9 / 37 games only where every game has a reference (not here)
    same = np.median([paper_raw(g, "DQN") for g in ("BeamRider", "DemonAttack", "Zaxxon")])
    assert on["agents"]["dqn"]["paper_same_games"] == pytest.approx(same)
    assert off["agents"]["dqn"]["paper_same_games"] == pytest.approx(
        np.median([paper_raw("Pong", "DQN"), paper_raw("Breakout", "DQN")])
    )
    assert on["agents"]["dqn"]["paper_all_games"] is None
    assert "without numbers" in med["note"]
    # with the shipped references the paper's median over all 9 tuning games is a number
    from rlu.evaluation.scores import load_reference_scores, normalized_score

    rnd, best = (
        load_reference_scores("random_scores"),
        load_reference_scores("atari_best_behaviour"),
    )
    shipped = build_report(dqn_records(), reps=100)["domains"]["atari"]["atari_median"]
    from rlu.tasks import list_tasks

    all9 = [
        float(normalized_score(paper_raw(t.name, "DQN"), rnd[t.id], best[t.id]))
        for t in list_tasks("atari", "online")
    ]
    assert shipped["online"]["agents"]["dqn"]["paper_all_games"] == pytest.approx(np.median(all9))
    # the Markdown row and the figure's bars hold the same numbers
    sweep = tmp_path / "s"
    sweep.mkdir()
    (sweep / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in dqn_records()))
    write_report(sweep, tmp_path / "r", *REFS, figures=False)
    md = (tmp_path / "r" / "report.md").read_text()
    # beside the paper's table, each row says which conditions of the paper's numbers it misses
    label = "(not comparable: preset, budget, data, episodes, seeds, selection)"
    (row,) = [
        x for x in md.splitlines() if x.startswith(f"| online (tuning games) | dqn {label} |")
    ]
    assert row.startswith(f"| online (tuning games) | dqn {label} | 3 of 9 | 50.0 | [")
    assert row.endswith(f"] | {same:.1f} |  |")  # no paper median over all 9 games here
    assert f"| naive offline (held-out) | dqn {label} | 2 of 37 | 47.5 |" in md


def test_per_game_normalised_improvement_by_hand():
    rep = build_report(dqn_records(), random_scores=REFS[0], best_behaviour=REFS[1], reps=100)
    bars = rep["domains"]["atari"]["atari_per_game"]["agents"]["dqn"]
    # each game under its own protocol: online choice on tuning games, naive choice (a) on
    # held-out ones; improvement = normalised - 100, best first
    got = [(b["task"], b["selection"], b["config"], b["improvement"]) for b in bars]
    assert got == [
        ("atari/DemonAttack", "online", "b", 0.0),
        ("atari/Pong", "offline", "a", -10.0),
        ("atari/BeamRider", "online", "a", -50.0),
        ("atari/Zaxxon", "online", "a", -70.0),
        ("atari/Breakout", "offline", "a", -95.0),
    ]
    for b in bars:
        game = b["task"].split("/")[1]
        assert b["paper_improvement"] == pytest.approx(paper_raw(game, "DQN") - 100.0)


def iqn_records():
    # (task, num_tau_samples, learning_rate) -> score; per game and tau the best lr counts
    table = {
        ("atari/BeamRider", 8, 1e-4): 20,
        ("atari/BeamRider", 8, 3e-5): 40,
        ("atari/DemonAttack", 8, 1e-4): 60,
        ("atari/DemonAttack", 8, 3e-5): 10,
        ("atari/Zaxxon", 8, 1e-4): 5,
        ("atari/Zaxxon", 8, 3e-5): 15,  # tau 8: 40 60 15 -> median 40
        ("atari/BeamRider", 16, 1e-4): 80,
        ("atari/BeamRider", 16, 3e-5): 70,
        ("atari/DemonAttack", 16, 1e-4): 30,
        ("atari/DemonAttack", 16, 3e-5): 90,
        ("atari/Zaxxon", 16, 1e-4): 50,  # tau 16: 80 90 50 -> median 80
        ("atari/Pong", 8, 1e-4): 1000,  # a held-out game: not in the ablation
    }
    out = []
    for (task, tau, lr), v in table.items():
        ov = {"learning_rate": lr, "num_tau_samples": tau}
        label = f"learning_rate={lr},num_tau_samples={tau}"
        out.append(rec(task, "iqn", label, 0, v, ov))
    return out


def test_iqn_tau_sensitivity_by_hand():
    rep = build_report(iqn_records(), random_scores=REFS[0], best_behaviour=REFS[1], reps=300)
    dom = rep["domains"]["atari"]
    panel = dom["iqn_tau"]
    assert panel["field"] == "num_tau_samples" and panel["games"] == TUNING and panel["of"] == 9
    assert [v["value"] for v in panel["values"]] == [8, 16]
    assert [v["median"] for v in panel["values"]] == [40.0, 80.0]
    assert [v["games"] for v in panel["values"]] == [3, 3]
    assert panel["values"][1]["configs"]["atari/DemonAttack"].startswith("learning_rate=3e-05")
    assert panel["paper"] == {"grid": [8, 16, 32], "best": 16, "numbers": None}
    # no bcq in this sweep: the BCQ figure is left out with the reason
    assert "bcq_threshold" not in dom["panels"]
    assert dom["absent"]["bcq_threshold"] == "the sweep has no bcq runs"


def test_bcq_threshold_sensitivity_and_its_reasons():
    recs = [
        rec(t, "bcq", f"threshold={th}", s, v + 10 * s, {"threshold": th})
        for t in TUNING
        for th, v in ((0.25, 30.0), (0.5, 70.0), (1.0, 10.0))
        for s in (0, 1)
    ]
    dom = build_report(recs, random_scores=REFS[0], best_behaviour=REFS[1], reps=100)["domains"]
    panel = dom["atari"]["bcq_threshold"]
    assert [(v["value"], v["median"]) for v in panel["values"]] == [
        (0.25, 35.0),
        (0.5, 75.0),
        (1.0, 15.0),
    ]
    # one threshold only: no figure, and the reason names the grid that draws it
    one = [r for r in recs if r["overrides"]["threshold"] == 0.5]
    dom = build_report(one, random_scores=REFS[0], best_behaviour=REFS[1], reps=100)["domains"]
    why = dom["atari"]["absent"]["bcq_threshold"]
    assert "1 value(s) of threshold" in why and "[0.25, 0.5, 0.75, 1.0]" in why
    # held-out games only: the ablation is over the tuning games
    off = [{**r, "task": "atari/Pong"} for r in recs if r["task"] == "atari/BeamRider"]
    dom = build_report(off, random_scores=REFS[0], best_behaviour=REFS[1], reps=100)["domains"]
    assert "sweep has none of them" in dom["atari"]["absent"]["bcq_threshold"]


def test_panels_without_data_say_why_in_one_line(tmp_path):
    """Unnormalised Atari (a game without reference scores), held-out games only: each panel
    that applies but has no data is one line in the report, and nothing else breaks."""
    sweep = tmp_path / "s"
    sweep.mkdir()
    recs = [{**r, "task": t} for r in dqn_records() if r["task"] == "atari/Pong" for t in HELD_OUT]
    (sweep / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    write_report(sweep, tmp_path / "r", random_scores={}, best_behaviour={}, figures=False)
    md = (tmp_path / "r" / "report.md").read_text()
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    absent = rep["domains"]["atari"]["absent"]
    assert set(absent) == {
        "online",
        "offline_naive",
        "aggregates",
        "atari_median",
        "atari_per_game",
        "iqn_tau",
        "bcq_threshold",
        "curves",  # records without run folders
        "profiles",
        "improvement",
    }
    for title in (
        "Atari median normalised score (the paper's Atari figure): left out, Atari scores are "
        "compared normalised",
        "Atari per-game normalised improvement: left out, Atari scores are compared normalised",
        "Aggregates over tasks: left out, Atari scores are compared normalised",
        "IQN tau-samples sensitivity: left out, the sweep has no iqn runs.",
        "Offline policy selection (naive): left out, naive offline selection chooses a "
        "configuration on the online-selection tasks",
        # the held-out games are never shown with their per-task best configuration
        "Online policy selection: left out, the sweep has no online-selection task",
    ):
        assert md.count(title) == 1, title
    # normalised but held-out games only: the median figure has no half to draw
    dom = build_report(recs, random_scores=REFS[0], best_behaviour=REFS[1], reps=100)
    why = dom["domains"]["atari"]["absent"]["atari_median"]
    assert "none of the 9 tuning games" in why and "naive offline selection" in why


def test_task_bars_put_each_task_under_its_own_protocol():
    online, offline = "control_suite/cartpole_swingup", "control_suite/walker_walk"
    table = {
        (online, "a"): [500, 520],
        (online, "b"): [100, 120],
        (offline, "a"): [300, 310],
        (offline, "b"): [900, 910],  # better, but naive selection keeps a
    }
    recs = [rec(t, "bc", c, s, v) for (t, c), vals in table.items() for s, v in enumerate(vals)]
    dom = build_report(recs, reps=100)["domains"]["control_suite"]
    bars = dom["task_bars"]
    assert [r["task"] for r in bars["online"]] == [online]
    assert [r["task"] for r in bars["offline"]] == [offline]
    assert bars["online"][0]["cells"]["bc"]["config"] == "a"
    assert bars["chosen"] == {"bc": "a"}
    row = bars["offline"][0]
    cell = row["cells"]["bc"]
    assert (cell["config"], cell["mean"]) == ("a", 305.0)
    assert cell["std"] == pytest.approx(np.std([300, 310], ddof=1))  # the sample std
    assert row["paper"]["bc"] == load_paper_results()["control_suite"]["Walker walk"]["BC"]
    # the online table holds the online tasks only: never the offline task's per-task best (905)
    assert [r["task"] for r in dom["online"]["rows"]] == [online]
    off = dom["offline_naive"]["rows"]
    assert [r["task"] for r in off] == [offline] and off[0]["cells"]["bc"]["mean"] == 305.0
    # no Atari figure panels outside Atari, no per-task bars in Atari
    assert not {"atari_median", "atari_per_game", "iqn_tau"} & set(dom["panels"] + [*dom["absent"]])
    atari = build_report(dqn_records(), random_scores=REFS[0], best_behaviour=REFS[1], reps=50)[
        "domains"
    ]["atari"]
    assert "task_bars" not in atari["panels"] and "task_bars" not in atari["absent"]


# --- figures ---------------------------------------------------------------------------------
def _figure_report():
    recs = dqn_records() + iqn_records()
    recs += [
        rec(t, "bcq", f"threshold={th}", 0, v, {"threshold": th})
        for t in TUNING + HELD_OUT
        for th, v in ((0.25, 20.0), (0.5, 60.0))
    ]
    return build_report(recs, random_scores=REFS[0], best_behaviour=REFS[1], reps=200)


def test_atari_figures_draw_the_panels_numbers():
    pytest.importorskip("matplotlib")
    from rlu.report.render import (
        atari_median_figure,
        atari_per_game_figure,
        pyplot,
        sensitivity_figure,
    )
    from tests.evaluation.test_report import _layout_problems

    plt = pyplot()
    dom = _figure_report()["domains"]["atari"]
    fig = atari_median_figure(dom, plt)
    try:
        assert _layout_problems(fig) == [] and fig.legends
        for ax, half in zip(fig.axes, ("online", "offline"), strict=True):
            agents = dom["atari_median"][half]["agents"]
            names = [a for a in dom["agents"] if a in agents]
            heights = [p.get_height() for p in ax.patches]
            assert heights == pytest.approx([agents[a]["median"] for a in names])
            assert [t.get_text() for t in ax.get_xticklabels()] == names
            games = len(dom["atari_median"][half]["games"])
            assert f"{games} of {9 if half == 'online' else 37}" in ax.get_title()
    finally:
        plt.close(fig)
    fig = atari_per_game_figure(dom, plt)
    try:
        assert _layout_problems(fig) == []
        per = dom["atari_per_game"]["agents"]
        for ax, a in zip(fig.axes, [a for a in dom["agents"] if a in per], strict=True):
            assert [p.get_height() for p in ax.patches] == pytest.approx(
                [b["improvement"] for b in per[a]]
            )
            assert ax.get_title() == a
    finally:
        plt.close(fig)
    for name in ("iqn_tau", "bcq_threshold"):
        fig = sensitivity_figure(dom[name], name, plt)
        try:
            assert _layout_problems(fig) == []
            (ax,) = fig.axes
            (squares,) = [ln for ln in ax.lines if ln.get_marker() == "s"]
            ys = squares.get_ydata()
            assert list(ys) == pytest.approx([v["median"] for v in dom[name]["values"]])
            labels = [t.get_text() for t in ax.get_xticklabels()]
            assert labels == [str(v["value"]) for v in dom[name]["values"]]
        finally:
            plt.close(fig)


def test_task_figure_shows_online_and_offline_groups():
    pytest.importorskip("matplotlib")
    from rlu.report.render import pyplot, tasks_figure
    from tests.evaluation.test_report import CONTROL, _layout_problems, records

    plt = pyplot()
    dom = build_report(records(CONTROL, ["bc", "d4pg"]), reps=50)["domains"]["control_suite"]
    dom["dataset_p90"] = {t: 450.0 + i for i, t in enumerate(dom["tasks"])}
    fig = tasks_figure(dom, "control_suite", plt)
    try:
        assert _layout_problems(fig) == []
        groups = [sf._suptitle.get_text() for sf in fig.subfigs]
        assert groups[0] == "online policy selection" and groups[1].startswith("offline")
        bars = dom["task_bars"]
        rows = bars["online"] + bars["offline"]
        drawn = [ax for ax in fig.axes if ax.axison]
        assert [ax.get_title() for ax in drawn] == [r["task"].split("/")[1] for r in rows]
        for ax, row in zip(drawn, rows, strict=True):
            heights = [p.get_height() for p in ax.patches]
            assert heights == pytest.approx([row["cells"][a]["mean"] for a in dom["agents"]])
            p90 = [ln.get_ydata()[0] for ln in ax.lines if ln.get_linestyle() == "--"]
            assert p90 == [dom["dataset_p90"][row["task"]]]
    finally:
        plt.close(fig)


# --- several sweeps ----------------------------------------------------------------------------
def _sweep(path: Path, recs, datasets=None) -> Path:
    path.mkdir(parents=True)
    (path / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    if datasets is not None:
        (path / "sweep.json").write_text(json.dumps({"datasets": datasets}))
    return path


def test_several_sweeps_in_one_report(tmp_path, capsys):
    pytest.importorskip("jinja2")
    from rlu.cli import main

    control = [rec("control_suite/cartpole_swingup", "bc", "default", s, 300.0 + s) for s in (0, 1)]
    a = _sweep(tmp_path / "atari", dqn_records())
    c = _sweep(tmp_path / "control", control)
    write_report([a, c], tmp_path / "r", *REFS, figures=False)
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    assert sorted(rep["domains"]) == ["atari", "control_suite"]
    assert "atari_median" in rep["domains"]["atari"]["panels"]
    # several sweeps need --out; an overlapping run or a task with two datasets is an error
    with pytest.raises(RluError, match="pass --out"):
        write_report([a, c])
    assert main(["report", str(a), str(c)]) == 2
    assert "pass --out" in capsys.readouterr().err
    again = _sweep(tmp_path / "again", dqn_records()[:1])
    with pytest.raises(RluError, match="and so is .* with the same settings"):
        write_report([a, again], tmp_path / "r2")
    d1 = _sweep(tmp_path / "d1", control[:1], {"control_suite/cartpole_swingup": "/data/x"})
    d2 = _sweep(tmp_path / "d2", control[1:], {"control_suite/cartpole_swingup": "/data/y"})
    assert not (tmp_path / "r2").exists()
    # one task, two datasets: grouped all the same (each cell says what produced it); no one
    # dataset's 90th percentile is the task's line, and the report says why
    write_report([d1, d2], tmp_path / "r3", figures=False)
    dom = json.loads((tmp_path / "r3" / "report.json").read_text())["domains"]["control_suite"]
    assert dom["datasets"] == {"control_suite/cartpole_swingup": ["/data/x", "/data/y"]}
    assert dom["dataset_p90"] == {"control_suite/cartpole_swingup": None}
    assert "| control_suite/cartpole_swingup | online | none: its runs used 2 datasets |" in (
        (tmp_path / "r3" / "report.md").read_text()
    )


def test_rwrl_challenges_are_reported_apart(tmp_path):
    """RWRL results evaluated under the easy challenge are their own row, as the paper's RWRL
    results are; the same task's ``none`` results stay under the plain task."""
    none = [
        {
            **rec("rwrl/walker_walk", "bc", "default", s, 500.0 + s),
            "env_settings": {"challenge": "none"},
        }
        for s in (0, 1)
    ]
    easy = [
        {
            **rec("rwrl/walker_walk", "bc", "default", s, 100.0 + s),
            "env_settings": {"challenge": "easy"},
        }
        for s in (0, 1)
    ]
    from rlu.data import Schema
    from rlu.data.synthetic import write_synthetic
    from rlu.tasks import get_task

    schema = Schema.for_task(get_task("rwrl/walker_walk"))
    data = {c: str(write_synthetic(tmp_path / f"data_{c}", schema, 2, 5)) for c in ("none", "easy")}
    a = _sweep(tmp_path / "none", none, {"rwrl/walker_walk": data["none"]})
    b = _sweep(tmp_path / "easy", easy, {"rwrl/walker_walk": data["easy"]})
    write_report([a, b], tmp_path / "r", *REFS, figures=False)
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    rwrl = rep["domains"]["rwrl"]
    assert rwrl["tasks"] == ["rwrl/walker_walk", "rwrl/walker_walk:easy"]
    means = {row["task"]: row["cells"]["bc"]["mean"] for row in rwrl["online"]["rows"]}
    assert means == {"rwrl/walker_walk": 500.5, "rwrl/walker_walk:easy": 100.5}
    assert set(rwrl["dataset_p90"]) == set(means)  # each challenge with its own dataset
    assert "| rwrl/walker_walk:easy |" in (tmp_path / "r" / "report.md").read_text()


# --- rlu report over real sweeps ---------------------------------------------------------------
@pytest.mark.slow
def test_rlu_report_renders_every_panel_of_real_sweeps(tmp_path, capsys):
    """Two tiny sweeps trained and evaluated for real (synthetic data in each task's schema,
    real ALE and dm_control evaluation): 2 tuning + 2 held-out Atari games with bc, bcq (2
    thresholds) and iqn (2 tau counts); 2 control tasks with bc, bcq and d4pg. ``rlu report``
    over both writes every panel of the paper's figures, and the Atari median is recomputed
    here from results.jsonl and the shipped reference scores."""
    pytest.importorskip("matplotlib")
    pytest.importorskip("ale_py")
    pytest.importorskip("dm_control")
    from rlu.cli import main
    from rlu.data.store import Schema
    from rlu.data.synthetic import write_synthetic
    from rlu.evaluation.scores import load_reference_scores, normalized_score
    from rlu.tasks import get_task

    atari = ["atari/BeamRider", "atari/Zaxxon", "atari/Pong", "atari/Breakout"]
    control = ["control_suite/cartpole_swingup", "control_suite/walker_walk"]
    data = {}
    for i, t in enumerate(atari + control):
        path = tmp_path / "data" / t.replace("/", "_")
        data[t] = str(write_synthetic(path, Schema.for_task(get_task(t)), 3, 40, seed=i))
    common = ["--steps", "3", "--eval-episodes", "1", "--eval-envs", "1", "--checkpoint-every",
              "3", "--log-every", "1", "--workers", "2"]  # fmt: skip
    sweeps = {}
    # evaluation episodes cut at 400 Atari / 100 control steps: seconds per run, and enough
    # steps for some games to score
    for name, tasks, agents, seeds, max_steps in (
        ("atari", atari, ["bc", "bcq", "iqn"], ["0"], "400"),
        ("control", control, ["bc", "bcq", "d4pg"], ["0", "1"], "100"),
    ):
        sweeps[name] = tmp_path / name
        argv = ["sweep", "--tasks", *tasks, "--agents", *agents, "--seeds", *seeds,
                "--max-configs", "2", "--eval-max-steps", max_steps, "--out", str(sweeps[name]),
                *common]  # fmt: skip
        for t in tasks:
            argv += ["--dataset", f"{t}={data[t]}"]
        assert main(argv) == 0
    out = tmp_path / "report"
    assert main(["report", str(sweeps["atari"]), str(sweeps["control"]), "--out", str(out)]) == 0
    rep = json.loads((out / "report.json").read_text())
    a, c = rep["domains"]["atari"], rep["domains"]["control_suite"]
    assert a["absent"] == {} and c["absent"] == {}
    assert a["panels"] == ["online", "offline_naive", "aggregates", "dataset_p90", "atari_median",
                           "atari_per_game", "iqn_tau", "bcq_threshold", "curves", "profiles",
                           "improvement"]  # fmt: skip
    assert c["panels"] == ["online", "offline_naive", "aggregates", "dataset_p90", "task_bars",
                           "curves", "profiles", "improvement"]  # fmt: skip
    assert [v["value"] for v in a["iqn_tau"]["values"]] == [8, 16]
    assert [v["value"] for v in a["bcq_threshold"]["values"]] == [0.25, 0.5]
    figures = sorted(p.name for p in (out / "figures").iterdir())
    assert figures == ["atari_curves.png", "atari_improvement.png", "atari_median.png",
                       "atari_per_game.png", "atari_profiles.png", "bcq_threshold.png",
                       "control_suite_curves.png", "control_suite_improvement.png",
                       "control_suite_profiles.png", "control_suite_tasks.png",
                       "iqn_tau.png"]  # fmt: skip
    md, html = (out / "report.md").read_text(), (out / "report.html").read_text()
    for f in figures:
        png = (out / "figures" / f).read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000, f
        assert f"(figures/{f})" in md and f'src="figures/{f}"' in html
    # the online half of the Atari figure, from the run records and the shipped references
    rnd, best = (
        load_reference_scores("random_scores"),
        load_reference_scores("atari_best_behaviour"),
    )
    records = [json.loads(x) for x in (sweeps["atari"] / "results.jsonl").read_text().splitlines()]
    for agent in ("bc", "bcq", "iqn"):
        per_game = []
        for game in ("atari/BeamRider", "atari/Zaxxon"):
            by_cfg = {}
            for r in records:
                if (r["task"], r["agent"]) == (game, agent):
                    by_cfg.setdefault(r["config"], []).append(r["score"])
            assert len(by_cfg) == 2  # two configurations per agent (--max-configs 2)
            raw = max(np.mean(v) for v in by_cfg.values())
            per_game.append(float(normalized_score(raw, rnd[game], best[game])))
        got = a["atari_median"]["online"]["agents"][agent]
        assert got["median"] == pytest.approx(np.median(per_game)) and got["games"] == 2
    label = "(not comparable: preset, budget, data, episodes, seeds, selection)"
    assert f"| online (tuning games) | iqn {label} | 2 of 9 |" in md
    assert f"| naive offline (held-out) | bcq {label} | 2 of 37 |" in md
