"""rlu report says what produced every number (issue 29): each cell's preset, learner steps,
data and evaluation episodes; the paper's numbers beside them headed as a comparison only where
the cell ran the paper's settings (paper preset, its full budget, the release's data); and each
split's aggregate under its own protocol, never mixed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rlu.evaluation.report import build_report, not_comparable, run_provenance, write_report
from rlu.types import RluError

CARTPOLE, STAND = "control_suite/cartpole_swingup", "control_suite/walker_stand"  # online
WALK = "control_suite/walker_walk"  # offline
RELEASE = {"source": "release", "family": "control_suite", "files": 1}
GENERATED = {"source": "generated", "scale": "laptop", "command": "rlu generate x --scale laptop"}


def paper_steps(agent: str, discrete: bool) -> int | None:
    """What ``rlu report`` passes to ``write_report`` (the report's package may not import the
    agents)."""
    pytest.importorskip("torch")
    from rlu.agents import paper_steps as budget

    return budget(agent, discrete)


def rec(task, agent, config, seed, score, **fields):
    r = {"task": task, "agent": agent, "config": config, "seed": seed, "score": float(score),
         "run": f"{task}/{agent}/{config}/{seed}"}  # fmt: skip
    defaults = {"preset": "small", "steps": 300, "pretrain_steps": 0, "eval_episodes": 5,
                "data": GENERATED}  # fmt: skip
    return {**r, **defaults, **fields}


def sweep(path: Path, recs) -> Path:
    path.mkdir(parents=True)
    (path / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    return path


def md_rows(md: str, start: str) -> list[list[str]]:
    return [
        [c.strip() for c in line.strip("|").split("|")]
        for line in md.splitlines()
        if line.startswith(start)
    ]


# --- the protocols ---------------------------------------------------------------------------
def disagreeing_sweep():
    """A grid whose two protocols disagree: online selection per task would take config b on
    the offline task (1200), naive offline selection keeps a (400), the config that is best on
    the online task (500 against 400). The old headline, online selection over every task,
    averaged 500 and 1200 into 850; each task under its own protocol averages to 450."""
    table = {(CARTPOLE, "a"): 500, (CARTPOLE, "b"): 400, (WALK, "a"): 400, (WALK, "b"): 1200}
    return [
        rec(t, "bc", c, s, v + d) for (t, c), v in table.items() for s, d in ((0, -10.0), (1, 10.0))
    ]


def test_aggregates_follow_each_splits_protocol_and_never_mix(tmp_path):
    pytest.importorskip("jinja2")
    dom = build_report(disagreeing_sweep(), reps=200)["domains"]["control_suite"]
    agg = dom["aggregates"]
    on, off = agg["online"], agg["offline"]
    assert on["tasks"] == [CARTPOLE] and on["agents"]["bc"]["mean"] == pytest.approx(500.0)
    assert off["tasks"] == [WALK] and off["chosen"] == {"bc": "a"}
    assert off["agents"]["bc"]["mean"] == pytest.approx(400.0)
    assert off["agents"]["bc"]["iqm"] == pytest.approx(400.0)  # 390, 410: nothing trimmed
    # neither the mixed oracle (850) nor a mix of the two protocols (450) is an aggregate
    every = [e["mean"] for half in (on, off) for e in half["agents"].values()]
    assert not {850.0, 450.0} & {round(x, 6) for x in every}
    # the online table holds the online task only; the offline task is under naive selection
    assert [r["task"] for r in dom["online"]["rows"]] == [CARTPOLE]
    assert [r["task"] for r in dom["offline_naive"]["rows"]] == [WALK]
    assert dom["offline_naive"]["rows"][0]["cells"]["bc"]["config"] == "a"
    # the Markdown names each row's protocol, and the caption says they are never mixed
    write_report(sweep(tmp_path / "s", disagreeing_sweep()), tmp_path / "r", figures=False)
    md = (tmp_path / "r" / "report.md").read_text()
    rows = md_rows(md, "| online policy selection, ") + md_rows(md, "| naive offline selection")
    assert [(r[0], r[1], r[2], r[3]) for r in rows] == [
        ("online policy selection, online-selection tasks", "bc", "1", "500.0"),
        ("naive offline selection, offline-selection tasks", "bc", "1", "400.0"),
    ]
    assert "each split under its own protocol and never mixed" in md
    assert "1200.0" not in md and "850.0" not in md


def test_an_agent_with_one_configuration_needs_no_selection():
    """Offline tasks only, one configuration per agent: nothing to select, so the naive table
    holds it; with two configurations and no online task, the reason is given."""
    one = [rec(WALK, "bc", "default", s, 300 + s) for s in (0, 1)]
    dom = build_report(one, reps=50)["domains"]["control_suite"]
    assert dom["offline_naive"]["only_configuration"] == ["bc"]
    assert dom["aggregates"]["offline"]["agents"]["bc"]["mean"] == pytest.approx(300.5)
    assert "no online-selection task" in dom["absent"]["online"]
    two = one + [rec(WALK, "bc", "other", s, 900) for s in (0, 1)]
    dom = build_report(two, reps=50)["domains"]["control_suite"]
    assert "ran 2 configurations" in dom["absent"]["offline_naive"]
    assert "aggregates" in dom["absent"] and "offline_naive" not in dom["panels"]


# --- what produced a number ------------------------------------------------------------------
def test_comparable_only_with_the_paper_preset_its_budget_and_the_release():
    budget = paper_steps("bc", False)
    assert budget == 1_000_000 and paper_steps("dqn", True) == 2_000_000
    assert paper_steps("no_such_agent", False) is None
    full = run_provenance(rec(CARTPOLE, "bc", "a", 0, 1, preset="paper", steps=budget,
                              data=RELEASE))  # fmt: skip
    assert not_comparable(full, budget) == []
    cases = {
        "preset small, not paper": {"preset": "small"},
        "999,999 of the paper preset's 1,000,000 learner steps": {"steps": budget - 1},
        "generated data, not the release's": {"data": GENERATED},
        "learner steps not recorded": {"steps": None},
    }
    for why, change in cases.items():
        p = run_provenance(rec(CARTPOLE, "bc", "a", 0, 1, **{**full, **change}))
        assert not_comparable(p, budget) == [why]
    # a report not told the budget claims no comparison
    assert not_comparable(full, None) == [
        "the paper preset's learner budget was not given to the report"
    ]


def test_older_records_and_bad_sources():
    """A record from before runs recorded their data counts as source unknown, its evaluation
    episodes its final returns; a source that is not one of the five is an error naming it."""
    old = {"task": CARTPOLE, "agent": "bc", "config": "a", "seed": 0, "score": 1.0,
           "preset": "small", "returns": [1.0, 2.0, 3.0], "run": "r0"}  # fmt: skip
    assert run_provenance(old) == {
        "preset": "small",
        "steps": None,
        "pretrain_steps": None,
        "eval_episodes": 3,
        "data": {"source": "unknown"},
    }
    dom = build_report([old], reps=20)["domains"]["control_suite"]
    assert dom["online"]["rows"][0]["cells"]["bc"]["not_comparable"] == [
        "preset small, not paper",
        "the paper preset's learner budget was not given to the report",
        "unknown data, not the release's",
    ]
    with pytest.raises(RluError, match=r"run r0: field data.source is 'laptop'"):
        build_report([{**old, "data": {"source": "laptop"}}])


def mixed_sweep():
    """bc ran the paper's settings on cartpole and walker stand; d4pg the small preset on
    cartpole; bc's walker-stand seeds stopped at half the budget."""
    budget = 1_000_000
    paper = {"preset": "paper", "steps": budget, "data": RELEASE, "eval_episodes": 10}
    return (
        [rec(CARTPOLE, "bc", "default", s, 380 + s, **paper) for s in (0, 1)]
        + [rec(STAND, "bc", "default", s, 390 + s, **{**paper, "steps": budget // 2})
           for s in (0, 1)]
        + [rec(CARTPOLE, "d4pg", "default", s, 700 + s) for s in (0, 1)]
    )  # fmt: skip


def test_every_cell_says_what_produced_it_and_the_paper_columns_say_if_they_compare(tmp_path):
    pytest.importorskip("jinja2")
    write_report(sweep(tmp_path / "s", mixed_sweep()), tmp_path / "r", figures=False,
                 paper_steps=paper_steps)  # fmt: skip
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    dom = rep["domains"]["control_suite"]
    assert dom["paper_budgets"] == {"bc": 1_000_000, "d4pg": 1_000_000}
    entries = [(p["preset"], p["steps"], p["data"]["source"], p["runs"], p["comparable_runs"])
               for p in dom["provenance"]]  # fmt: skip
    assert sorted(entries) == [
        ("paper", 500_000, "release", 2, 0),
        ("paper", 1_000_000, "release", 2, 2),
        ("small", 300, "generated", 2, 0),
    ]
    letter = {(p["preset"], p["steps"]): "ABC"[i] for i, p in enumerate(dom["provenance"])}
    rows = {r["task"]: r for r in dom["online"]["rows"]}
    assert rows[CARTPOLE]["cells"]["bc"]["comparable"]
    assert not rows[STAND]["cells"]["bc"]["comparable"]
    assert dom["online"]["paper_columns"] == {
        "bc": {"budget": 1_000_000, "comparable": "some"},
        "d4pg": {"budget": 1_000_000, "comparable": "none"},
    }
    md = (tmp_path / "r" / "report.md").read_text()
    (head,) = md_rows(md, "| task |")
    assert head == [
        "task",
        "bc",
        "bc: paper (1M steps, paper preset, release data): comparable only where marked",
        "d4pg",
        "d4pg: paper (1M steps, paper preset, release data): not comparable to these cells",
    ]
    cart, stand = md_rows(md, f"| {CARTPOLE}"), md_rows(md, f"| {STAND}")
    a, b, c = letter[("paper", 1_000_000)], letter[("paper", 500_000)], letter[("small", 300)]
    assert cart[0][1:] == [f"380.5 ± 0.5 [{a}]", "386.0 ± 6.0 (comparable)",
                           f"**700.5 ± 0.5 [{c}]**", "856.0 ± 13.0"]  # fmt: skip
    assert stand[0][1:3] == [f"**390.5 ± 0.5 [{b}]**", "386.0 ± 7.0 (not comparable)"]
    # the legend of the letters: every cell's preset, steps, data and evaluation episodes
    assert (
        f"[{c}] preset small, 300 learner steps, data generated by rlu (scale laptop, "
        "`rlu generate x --scale laptop`), 5 evaluation episodes per run" in md
    )
    assert f"[{b}] preset paper, 500,000 learner steps, data the release's files (family " in md
    assert "500,000 of the paper preset's 1,000,000 learner steps" in md
    (prov,) = [r for r in md_rows(md, f"| {c} |")]
    assert prov[1:4] == ["small", "300", ""] and prov[-1] == "0 of 2"
    assert "2 of 6 runs did" in md
    html = (tmp_path / "r" / "report.html").read_text()
    assert "d4pg: paper (1M steps, paper preset, release data): not comparable to these cells" in (
        html
    )


def test_one_provenance_is_spelled_out_once_per_table(tmp_path):
    pytest.importorskip("jinja2")
    recs = [rec(CARTPOLE, a, "default", s, 300 + s) for a in ("bc", "d4pg") for s in (0, 1)]
    write_report(sweep(tmp_path / "s", recs), tmp_path / "r", figures=False,
                 paper_steps=paper_steps)  # fmt: skip
    md = (tmp_path / "r" / "report.md").read_text()
    assert "[A]" not in md  # one provenance: no letters on the cells
    assert md.count("Every number here: preset small, 300 learner steps, data generated") == 2
    (row,) = md_rows(md, f"| {CARTPOLE}")
    assert row[1:3] == ["**300.5 ± 0.5**", "386.0 ± 6.0"]
    assert "no run here did" in md
    # every cell ran the paper's settings: the paper's columns are a comparison
    full = [{**r, "preset": "paper", "steps": 1_000_000, "data": RELEASE} for r in recs]
    write_report(sweep(tmp_path / "s2", full), tmp_path / "r2", figures=False,
                 paper_steps=paper_steps)  # fmt: skip
    md = (tmp_path / "r2" / "report.md").read_text()
    (head,) = md_rows(md, "| task |")
    assert head[2] == "bc: paper (1M steps, paper preset, release data): comparable"
    assert "every run here ran them" in md


def test_figures_label_the_paper_markers_and_say_what_drew_the_bars():
    pytest.importorskip("matplotlib")
    from rlu.evaluation.report.render import atari_median_figure, pyplot, tasks_figure
    from tests.evaluation.test_report import _layout_problems

    plt = pyplot()
    dom = build_report(mixed_sweep(), reps=50, paper_steps=paper_steps)["domains"]
    fig = tasks_figure(dom["control_suite"], "control_suite", plt)
    try:
        assert _layout_problems(fig) == []
        labels = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
        assert labels == [
            "paper (1M steps, paper preset, release data): comparable only where the tables say so"
        ]
        title = fig._suptitle.get_text().replace("\n", " ")
        assert (
            "rlu's bars: preset small/paper, 300/1M/500k learner steps, data generated/release, "
            "5/10 evaluation episodes per run" in title
        )
    finally:
        plt.close(fig)
    games = ["atari/BeamRider", "atari/Pong"]
    atari = [rec(g, "dqn", "default", s, 50 + s, data={"source": "synthetic"})
             for g in games for s in (0, 1)]  # fmt: skip
    refs = {g: 0.0 for g in games}, {g: 100.0 for g in games}
    dom = build_report(atari, random_scores=refs[0], best_behaviour=refs[1], reps=50,
                       paper_steps=paper_steps)["domains"]["atari"]  # fmt: skip
    fig = atari_median_figure(dom, plt)
    try:
        assert _layout_problems(fig) == []
        labels = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
        assert (
            "paper's table, same games, normalised (2M steps, paper preset, release data): not "
            "comparable to these bars" in labels
        )
        assert "data synthetic" in fig._suptitle.get_text().replace("\n", " ")
    finally:
        plt.close(fig)


def test_atari_panels_head_the_papers_table_as_not_comparable(tmp_path):
    pytest.importorskip("jinja2")
    games = ["atari/BeamRider", "atari/Zaxxon", "atari/Pong", "atari/Breakout"]
    recs = [rec(g, a, c, s, v + s, data={"source": "synthetic"}, steps=200)
            for g in games for a in ("dqn", "rem") for c, v in (("a", 40), ("b", 60))
            for s in (0, 1)]  # fmt: skip
    refs = {g: 0.0 for g in games}, {g: 100.0 for g in games}
    write_report(sweep(tmp_path / "s", recs), tmp_path / "r", *refs, figures=False,
                 paper_steps=paper_steps)  # fmt: skip
    md = (tmp_path / "r" / "report.md").read_text()
    (head,) = md_rows(md, "| selection | agent | games |")
    assert head[5] == (
        "paper's table, same games: paper (2M steps, paper preset, release data): not "
        "comparable to these cells"
    )
    (head,) = md_rows(md, "| game | selection |")
    assert (
        head[3]
        == "dqn: paper (2M steps, paper preset, release data): not comparable to these cells"
    )
    assert "Every number here: preset small, 200 learner steps, data synthetic" in md
    # the aggregates: each split under its protocol, the median for Atari
    rows = md_rows(md, "| online policy selection, ") + md_rows(md, "| naive offline selection")
    assert [(r[1], r[2], r[3]) for r in rows] == [
        ("dqn", "2", "60.5"),
        ("rem", "2", "60.5"),
        ("dqn", "2", "60.5"),
        ("rem", "2", "60.5"),
    ]
