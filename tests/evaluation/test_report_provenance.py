"""rlu report says what produced every number and compares it with the paper's only when every
condition of the paper's number holds (issue 40): the paper preset, the paper's budget (or,
where the paper states none, rlu's, said so), every release shard of the task, enough seeds and
evaluation episodes, and a selection whose inputs were themselves comparable. Each condition in
turn is missing here and the cell says which; with all of them it is comparable. The paper is
credited only with what it states."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from rlu.report import build_report, run_provenance, write_report
from rlu.types import RluError

CARTPOLE, STAND = "control_suite/cartpole_swingup", "control_suite/walker_stand"  # online
WALK = "control_suite/walker_walk"  # offline
ONLINE = ["control_suite/cartpole_swingup", "control_suite/cheetah_run",
          "control_suite/humanoid_run", "control_suite/manipulator_insert_ball", STAND]  # fmt: skip
ALL_SHARDS = {"source": "release", "family": "dm_control_suite", "files": 100, "steps": 40_000,
              "shards": {"used": 100, "of": 100, "dataset": ""}}  # fmt: skip
GENERATED = {"source": "generated", "scale": "laptop", "command": "rlu generate x --scale laptop"}


def paper(agent: str, discrete: bool):
    """What ``rlu report`` passes to ``write_report`` (the report's package may not import the
    agents): the agent's paper preset, read from its module."""
    pytest.importorskip("torch")
    from rlu.report.conditions import paper_preset

    return paper_preset(agent, discrete)


def rec(task, agent, config, seed, score, **fields):
    r = {"task": task, "agent": agent, "config": config, "seed": seed, "score": float(score),
         "run": f"{task}/{agent}/{config}/{seed}", "overrides": {}}  # fmt: skip
    defaults = {"preset": "small", "steps": 300, "pretrain_steps": 0, "eval_episodes": 5,
                "data": GENERATED}  # fmt: skip
    return {**r, **defaults, **fields}


FULL = {"preset": "paper", "steps": 1_000_000, "eval_episodes": 5, "data": ALL_SHARDS}
"""Every run condition of the paper's numbers for a continuous agent without a grid (bc)."""


def full(task, agent="bc", seeds=(0, 1, 2), base=380.0, **change):
    return [rec(task, agent, "default", s, base + s, **{**FULL, **change}) for s in seeds]


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


def cell(recs, task=CARTPOLE, agent="bc", table="online"):
    dom = build_report(recs, reps=50, paper=paper)["domains"]["control_suite"]
    (row,) = [r for r in dom[table]["rows"] if r["task"] == task]
    return row["cells"][agent]


# --- each condition in turn ------------------------------------------------------------------
def test_every_condition_holds_and_the_cell_is_comparable(tmp_path):
    pytest.importorskip("jinja2")
    c = cell(full(CARTPOLE))
    assert c["comparable"] and c["missing"] == [] and not any(c["conditions"].values())
    write_report(sweep(tmp_path / "s", full(CARTPOLE)), tmp_path / "r", figures=False,
                 paper=paper)  # fmt: skip
    md = (tmp_path / "r" / "report.md").read_text()
    (head,) = md_rows(md, "| task |")
    # the paper states no budget for the continuous baselines: the comparison is rlu's 1M, and
    # the heading says so
    assert head[2] == (
        "bc: paper (appendix B, table 'DM Control suite results'; the paper states no budget): "
        "comparable at rlu's 1M steps"
    )
    (row,) = md_rows(md, f"| {CARTPOLE}")
    assert row[1:3] == ["**381.0 ± 1.0 (comparable)**", "386.0 ± 6.0"]
    assert "Every run here meets the run conditions" in md


@pytest.mark.parametrize(
    "condition,change,why",
    [
        ("preset", {"preset": "small"}, "preset small, not paper"),
        ("budget", {"steps": 500_000},
         "500,000 learner steps, not rlu's 1M (the paper states no budget)"),
        ("data", {"data": {**ALL_SHARDS, "shards": {"used": 3, "of": 100, "dataset": ""}}},
         "3 of the release's 100 shards of the task"),
        ("data", {"data": GENERATED}, "generated data, not the release's"),
        ("data", {"data": {**ALL_SHARDS, "shards": {"used": 0, "of": None, "dataset": None},
                           "files": 1}},
         "1 files, none named as a release shard of the task"),
        ("episodes", {"eval_episodes": 2},
         "2 evaluation episodes, under rlu's 5 (the paper states no number of evaluation "
         "episodes)"),
    ],
)  # fmt: skip
def test_a_run_condition_missing_is_named_in_the_cell(condition, change, why):
    c = cell(full(CARTPOLE, **change))
    assert not c["comparable"] and c["missing"] == [condition]
    assert c["conditions"][condition] == why


def test_a_cell_of_too_few_seeds_says_seeds(tmp_path):
    pytest.importorskip("jinja2")
    c = cell(full(CARTPOLE, seeds=(0, 1)))
    assert c["missing"] == ["seeds"]
    assert c["conditions"]["seeds"] == (
        "2 seeds, under rlu's 3 (the paper states no number of seeds)"
    )
    write_report(sweep(tmp_path / "s", full(CARTPOLE, seeds=(0, 1))), tmp_path / "r",
                 figures=False, paper=paper)  # fmt: skip
    md = (tmp_path / "r" / "report.md").read_text()
    (row,) = md_rows(md, f"| {CARTPOLE}")
    assert row[1] == "**380.5 ± 0.7 (not comparable: seeds)**"


def test_overrides_outside_the_papers_grid_are_not_the_paper_preset():
    recs = [{**r, "config": "learning_rate=0.001", "overrides": {"learning_rate": 1e-3}}
            for r in full(CARTPOLE)]  # fmt: skip
    c = cell(recs)
    assert c["missing"] == ["preset"]
    assert c["conditions"]["preset"] == (
        "the paper preset changed outside the paper's grid (learning_rate=0.001)"
    )


def test_online_selection_among_runs_that_are_not_comparable_is_not():
    """The chosen configuration's runs meet every condition, but it was chosen over a
    configuration of small-preset runs: the selection's inputs were not comparable."""
    other = [rec(CARTPOLE, "bc", "learning_rate=0.001", s, 100.0 + s,
                 overrides={"learning_rate": 1e-3}) for s in (0, 1, 2)]  # fmt: skip
    c = cell(full(CARTPOLE) + other)
    assert c["config"] == "default" and c["missing"] == ["selection"]
    assert c["conditions"]["selection"] == (
        "chosen among runs that are not comparable (preset, budget, data)"
    )


def test_online_selection_must_have_seen_the_papers_whole_grid():
    """BRAC's paper grid is 3 x 3: one configuration of it, run with every other condition
    met, is not the paper's selection."""
    brac = paper("brac", False)
    assert brac.steps == 1_000_000 and len(brac.grid["alpha"]) * len(brac.grid["policy_lr"]) == 9
    overrides = {"alpha": 0.1, "policy_lr": 3e-5}
    recs = [{**r, "agent": "brac", "config": "alpha=0.1,policy_lr=3e-05", "overrides": overrides}
            for r in full(CARTPOLE)]  # fmt: skip
    c = cell(recs, agent="brac")
    assert c["missing"] == ["selection"]
    assert (
        c["conditions"]["selection"] == "1 of the paper grid's 9 configurations on cartpole_swingup"
    )
    every = [
        {**r, "agent": "brac", "config": f"a={a},p={p}", "overrides": {"alpha": a, "policy_lr": p},
         "score": r["score"] + (100 if (a, p) == (0.1, 3e-5) else 0)}
        for a in brac.grid["alpha"] for p in brac.grid["policy_lr"] for r in full(CARTPOLE)
    ]  # fmt: skip
    c = cell(every, agent="brac")
    assert c["comparable"] and c["config"] == "a=0.1,p=3e-05"


def test_naive_offline_selection_needs_comparable_runs_on_every_online_task():
    """An offline-selection task's cell: its configuration was chosen on the domain's
    online-selection tasks; with one of the five, or with one of them run on the small preset,
    the selection's inputs were not the paper's."""
    one = full(CARTPOLE) + full(WALK)
    c = cell(one, task=WALK, table="offline_naive")
    # bc ran one configuration: nothing to choose, and its grid has one
    assert c["comparable"], c["conditions"]
    two = one + [rec(CARTPOLE, "bc", "x", s, 10.0, overrides={"x": 1}) for s in (0, 1, 2)]
    c = cell(two, task=WALK, table="offline_naive")
    assert c["missing"] == ["selection"]
    assert c["conditions"]["selection"] == (
        "chosen on 1 of the domain's 5 online-selection tasks; chosen among runs that are not "
        "comparable (preset, budget, data)"
    )
    every = [r for t in ONLINE for r in full(t)] + full(WALK)
    every += [rec(t, "bc", "x", s, 10.0, **FULL, overrides={"x": 1}) for t in ONLINE
              for s in (0, 1, 2)]  # fmt: skip
    c = cell(every, task=WALK, table="offline_naive")
    # the second configuration changes a field outside BC's (empty) grid: not comparable input
    assert c["missing"] == ["selection"] and "(preset)" in c["conditions"]["selection"]
    every = [r for r in every if r["config"] == "default"]
    assert cell(every, task=WALK, table="offline_naive")["comparable"]


def test_atari_compares_at_the_papers_stated_budget_and_replay():
    """On Atari the paper states 2M learner steps and a 2M-step replay memory: those are the
    paper's numbers, and a run at them (and every other condition) is comparable."""
    pytest.importorskip("jinja2")
    lrs = paper("dqn", True).grid["learning_rate"]
    data = {"source": "release", "family": "atari", "files": 4, "steps": 2_000_000,
            "shards": {"used": 4, "of": 100, "dataset": "run_1"}}  # fmt: skip
    game = "atari/BeamRider"

    def runs(**change):
        base = {"preset": "paper", "steps": 2_000_000, "eval_episodes": 5, "data": data}
        return [rec(game, "dqn", f"learning_rate={lr}", s, 1000.0 + 100 * i + s,
                    overrides={"learning_rate": lr}, **{**base, **change})
                for i, lr in enumerate(lrs) for s in (0, 1, 2)]  # fmt: skip

    def atari_cell(recs):
        dom = build_report(recs, reps=50, paper=paper)["domains"]["atari"]
        return dom, dom["online"]["rows"][0]["cells"]["dqn"]

    dom, c = atari_cell(runs())
    assert c["comparable"], c["conditions"]
    assert dom["paper_presets"]["dqn"] == {"known": True, "steps": 2_000_000,
                                           "grid": {"learning_rate": list(lrs)},
                                           "budget": 2_000_000, "budget_stated": True}  # fmt: skip
    _, c = atari_cell(runs(steps=1_000_000))
    assert c["missing"] == ["budget", "selection"]
    assert c["conditions"]["budget"] == "1,000,000 learner steps, not the paper's 2M"
    _, c = atari_cell(runs(data={**data, "steps": 500_000}))
    assert c["conditions"]["data"] == (
        "500,000 steps of the release, under the paper's 2M-step replay"
    )


# --- the paper credited with what it states ----------------------------------------------------
def _paper_headings(md: str) -> list[str]:
    heads = [c for line in md.splitlines() if line.startswith("| ")
             for c in (x.strip() for x in line.strip("|").split("|"))]  # fmt: skip
    return [h for h in heads if re.match(r"^[\w.|' ,]+: paper \(", h)]


def test_no_budget_is_attributed_to_the_paper_that_it_does_not_state(tmp_path):
    """The column headings, the intro and the figure legend give the paper a budget only on
    Atari (its table 'Atari experiments hyperparameters': 2M); for the continuous baselines
    they say the paper states none, and name 1M as rlu's."""
    pytest.importorskip("matplotlib")
    cont = full(CARTPOLE) + full(CARTPOLE, agent="d4pg", steps=300, preset="small")
    games = ["atari/BeamRider", "atari/Pong"]
    atari = [rec(g, "dqn", "default", s, 50 + s, data={"source": "synthetic"})
             for g in games for s in (0, 1)]  # fmt: skip
    refs = {g: 0.0 for g in games}, {g: 100.0 for g in games}
    write_report([sweep(tmp_path / "c", cont), sweep(tmp_path / "a", atari)], tmp_path / "r",
                 *refs, paper=paper)  # fmt: skip
    md = (tmp_path / "r" / "report.md").read_text()
    heads = _paper_headings(md)
    cont_heads = [h for h in heads if "DM Control suite results" in h]
    atari_heads = [h for h in heads if "Atari 2600 results" in h]
    # control: bc and d4pg over the online table; Atari: dqn over the online and the naive
    # offline tables, the median figure's and the per-game table's
    assert len(cont_heads) == 2 and len(atari_heads) == 4
    for h in cont_heads:
        source = h.split(": paper (", 1)[1].split(")", 1)[0]
        assert source == "appendix B, table 'DM Control suite results'; the paper states no budget"
    assert cont_heads[0].endswith(": comparable at rlu's 1M steps")  # bc, every condition met
    assert cont_heads[1].endswith(": not comparable to these cells")  # d4pg, small preset
    for h in atari_heads:
        assert "appendix D, table 'Atari 2600 results'; 2M learner steps" in h
    intro = md.split("## control_suite", 1)[1].split("\n\n", 2)[1]
    assert "the paper states no learner budget: compared at rlu's 1M" in intro
    assert "1M" not in intro.replace("compared at rlu's 1M", "")
    control = md.split("## control_suite", 1)[1]
    (budget,) = md_rows(control, "| budget |")
    assert budget[1:] == [
        "nothing",
        "appendix A.1 gives no learner steps for the continuous baselines",
        "rlu's paper preset's learner steps (bc 1M, d4pg 1M): rlu's choice, the paper states none",
    ]
    atari_budget = md_rows(md.split("## atari", 1)[1].split("## control_suite")[0], "| budget |")
    assert atari_budget[0][1:3] == [
        "2M steps",
        "appendix A.2, table 'Atari experiments hyperparameters': 'Training Steps: 2M learning "
        "steps'",
    ]
    # the figure's legend of the paper's diamonds: the same source, no budget for the paper
    from rlu.report.render import pyplot, tasks_figure

    plt = pyplot()
    dom = json.loads((tmp_path / "r" / "report.json").read_text())["domains"]["control_suite"]
    fig = tasks_figure(dom, "control_suite", plt)
    try:
        labels = [t.get_text().replace("\n", " ") for leg in fig.legends for t in leg.get_texts()]
        assert ("paper (appendix B, table 'DM Control suite results'; the paper states no "
                "budget): comparable only where the tables say so") in labels  # fmt: skip
    finally:
        plt.close(fig)


# --- what produced a number ------------------------------------------------------------------
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
    c = build_report([old], reps=20)["domains"]["control_suite"]["online"]["rows"][0]["cells"]
    assert c["bc"]["conditions"] == {
        "preset": "the report knows no paper preset of this agent",
        "budget": "the paper preset's learner budget was not given to the report",
        "data": "unknown data, not the release's",
        "episodes": "3 evaluation episodes, under rlu's 5 (the paper states no number of "
        "evaluation episodes)",
        "seeds": "1 seed, under rlu's 3 (the paper states no number of seeds)",
        "selection": None,  # its only configuration: no other runs chosen among
    }
    with pytest.raises(RluError, match=r"run r0: field data.source is 'laptop'"):
        build_report([{**old, "data": {"source": "laptop"}}])


def mixed_sweep():
    """bc ran every condition on cartpole and stopped at half the budget on walker stand;
    d4pg the small preset on cartpole."""
    return (
        full(CARTPOLE)
        + full(STAND, steps=500_000, base=390.0)
        + [rec(CARTPOLE, "d4pg", "default", s, 700 + s) for s in (0, 1, 2)]
    )


def test_every_cell_says_what_produced_it_and_the_paper_columns_say_if_they_compare(tmp_path):
    pytest.importorskip("jinja2")
    write_report(sweep(tmp_path / "s", mixed_sweep()), tmp_path / "r", figures=False,
                 paper=paper)  # fmt: skip
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    dom = rep["domains"]["control_suite"]
    assert {a: p["budget"] for a, p in dom["paper_presets"].items()} == {
        "bc": 1_000_000, "d4pg": 1_000_000}  # fmt: skip
    entries = [(p["preset"], p["steps"], p["data"]["source"], p["runs"], p["comparable_runs"])
               for p in dom["provenance"]]  # fmt: skip
    assert sorted(entries) == [
        ("paper", 500_000, "release", 3, 0),
        ("paper", 1_000_000, "release", 3, 3),
        ("small", 300, "generated", 3, 0),
    ]
    letter = {(p["preset"], p["steps"]): "ABC"[i] for i, p in enumerate(dom["provenance"])}
    rows = {r["task"]: r for r in dom["online"]["rows"]}
    assert rows[CARTPOLE]["cells"]["bc"]["comparable"]
    assert rows[STAND]["cells"]["bc"]["missing"] == ["budget"]
    assert dom["online"]["paper_columns"] == {
        "bc": {"budget": 1_000_000, "budget_stated": False, "comparable": "some"},
        "d4pg": {"budget": 1_000_000, "budget_stated": False, "comparable": "none"},
    }
    md = (tmp_path / "r" / "report.md").read_text()
    (head,) = md_rows(md, "| task |")
    source = "appendix B, table 'DM Control suite results'; the paper states no budget"
    assert head == [
        "task",
        "bc",
        f"bc: paper ({source}): comparable only where marked at rlu's 1M steps",
        "d4pg",
        f"d4pg: paper ({source}): not comparable to these cells",
    ]
    cart, stand = md_rows(md, f"| {CARTPOLE}"), md_rows(md, f"| {STAND}")
    a, b, c = letter[("paper", 1_000_000)], letter[("paper", 500_000)], letter[("small", 300)]
    assert cart[0][1:] == [
        f"381.0 ± 1.0 [{a}] (comparable)",
        "386.0 ± 6.0",
        f"**701.0 ± 1.0 [{c}] (not comparable: preset, budget, data)**",
        "856.0 ± 13.0",
    ]
    assert stand[0][1:3] == [f"**391.0 ± 1.0 [{b}] (not comparable: budget)**", "386.0 ± 7.0"]
    # the legend of the letters: every cell's preset, steps, data and evaluation episodes
    assert (
        f"[{c}] preset small, 300 learner steps, data generated by rlu (scale laptop, "
        "`rlu generate x --scale laptop`), 5 evaluation episodes per run" in md
    )
    assert (
        f"[{b}] preset paper, 500,000 learner steps, data the release's files (family "
        "dm_control_suite, 100 of its 100 shards, 40,000 steps)" in md
    )
    assert ("budget: 300 learner steps, not rlu's 1M (the paper states no budget) / 500,000 "
            "learner steps, not rlu's 1M (the paper states no budget); data: ") in md  # fmt: skip
    (prov,) = [r for r in md_rows(md, f"| {c} |")]
    assert prov[1:4] == ["small", "300", ""] and prov[-1] == "0 of 3"
    assert "3 of 9 runs here meet the run conditions" in md


def test_one_provenance_is_spelled_out_once_per_table(tmp_path):
    pytest.importorskip("jinja2")
    recs = [rec(CARTPOLE, a, "default", s, 300 + s) for a in ("bc", "d4pg") for s in (0, 1)]
    write_report(sweep(tmp_path / "s", recs), tmp_path / "r", figures=False, paper=paper)
    md = (tmp_path / "r" / "report.md").read_text()
    assert "[A]" not in md  # one provenance: no letters on the cells
    assert md.count("Every number here: preset small, 300 learner steps, data generated") >= 2
    assert "No run here meets them" in md


def test_figures_label_the_paper_markers_and_say_what_drew_each_bar():
    pytest.importorskip("matplotlib")
    from rlu.report.render import pyplot, tasks_figure
    from tests.evaluation.test_report import _layout_problems

    plt = pyplot()
    recs = mixed_sweep() + [rec(STAND, "d4pg", "default", 0, 500.0)]  # a cell of one seed
    dom = build_report(recs, reps=50, paper=paper)["domains"]["control_suite"]
    fig = tasks_figure(dom, "control_suite", plt)
    try:
        assert _layout_problems(fig) == []
        title = fig._suptitle.get_text().replace("\n", " ")
        assert "mean ± sample std (ddof 1) over seeds" in title
        for i, p in enumerate(dom["provenance"]):  # every letter's data in the title
            assert f"[{'ABC'[i]}] preset {p['preset']}" in title
        assert "release (100 of 100 shards) data" in title
        (stand,) = [ax for ax in fig.axes if ax.get_title() == "walker_stand"]
        # each bar's letter above it; the one-seed bar hatched, without an error bar, "1" on it
        texts = sorted(t.get_text() for t in stand.texts)
        b = next("ABC"[i] for i, p in enumerate(dom["provenance"]) if p["steps"] == 500_000)
        c = next("ABC"[i] for i, p in enumerate(dom["provenance"]) if p["preset"] == "small")
        assert texts == sorted([b, f"1 {c}"])
        bars = [p for p in stand.patches if p.get_height() == p.get_height()]  # not the NaN key
        assert [bool(p.get_hatch()) for p in bars[:2]] == [False, True]
        (errs,) = [c for c in stand.containers if type(c).__name__ == "ErrorbarContainer"]
        assert len(errs.lines[2][0].get_segments()) == 1  # bc's only: d4pg has one seed
    finally:
        plt.close(fig)


def test_a_converted_release_dataset_records_the_shards_it_holds():
    """What the data condition reads: a release dataset's manifest names its shard files; they
    count against the registry's names for the task's dataset (a file named otherwise, such as
    a one-shard test fixture, counts as no release shard)."""
    from rlu.data.provenance import data_source
    from rlu.tasks import get_task

    names = get_task(CARTPOLE).release_dataset("dm_control_suite").shard_names("")
    prov = {"source": "rl_unplugged release", "family": "dm_control_suite", "task": CARTPOLE}
    some = [{"name": n.rsplit("/", 1)[-1]} for n in names[:3]]
    counts = {"steps": 1234}
    data = data_source({"provenance": {**prov, "files": some}, "counts": counts})
    assert data == {"source": "release", "family": "dm_control_suite", "files": 3,
                    "shards": {"used": 3, "of": 100, "dataset": ""}, "steps": 1234}  # fmt: skip
    every = [{"name": n.rsplit("/", 1)[-1]} for n in names]
    assert data_source({"provenance": {**prov, "files": every}})["shards"]["used"] == 100
    fixture = [{"name": "train-00000-of-00001"}]
    assert data_source({"provenance": {**prov, "files": fixture}})["shards"] == {
        "used": 0, "of": None, "dataset": None}  # fmt: skip
    # Atari: one run's shards are the dataset (run_1 of the five)
    pong = get_task("atari/Pong").release_dataset("atari").shard_names("run_2")[:4]
    data = data_source(
        {
            "provenance": {
                "source": "rl_unplugged release",
                "family": "atari",
                "task": "atari/Pong",
                "run": 2,
                "files": [{"name": n.rsplit("/", 1)[-1]} for n in pong],
            }
        }
    )
    assert data["shards"] == {"used": 4, "of": 100, "dataset": "run_2"}  # fmt: skip
