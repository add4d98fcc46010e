"""rlu report's rendering: Markdown and HTML from the numbers through the templates, figures
whose titles and legends fit, and the HTML as a real browser (headless chromium) draws it."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from rlu.report import build_report, write_report

CONTROL = ["control_suite/cartpole_swingup", "control_suite/walker_walk", "control_suite/fish_swim"]


def records(tasks, agents, seeds=(0, 1, 2), seed=0):
    """Result records of a fake sweep (the report is what is under test, not training)."""
    rng = np.random.default_rng(seed)
    return [
        {"task": t, "agent": a, "config": c, "seed": s, "score": float(rng.uniform(100, 800)),
         "run": f"{t}/{a}/{c}/{s}"}
        for t in tasks for a in agents for c in ("lr=1e-4", "lr=3e-4") for s in seeds
    ]  # fmt: skip


def write_sweep(path: Path, recs) -> Path:
    path.mkdir(parents=True)
    (path / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    return path


def test_markdown_and_html_hold_every_number_of_the_json(tmp_path):
    pytest.importorskip("jinja2")
    from rlu.report import render

    recs = records(CONTROL, ["bc", "d4pg", "tests.train.fake|agent"])
    write_report(write_sweep(tmp_path / "s", recs), tmp_path / "r", figures=False)
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    md = (tmp_path / "r" / "report.md").read_text()
    html = (tmp_path / "r" / "report.html").read_text()
    dom = rep["domains"]["control_suite"]
    assert dom["panels"] == ["online", "offline_naive", "aggregates", "task_bars", "profiles",
                             "improvement"]  # fmt: skip
    assert "curves" in dom["absent"]  # records without run folders: no eval.jsonl to draw
    # what produced the numbers, the paper's conditions, the online and naive offline tables,
    # the aggregates, the performance profiles and the probability of improvement
    assert html.count("<table>") == 7 and html.count("<section") == 1
    # each table scrolls in its own box: a wide one (five agents and the paper's columns) does
    # not push the page past the window
    assert html.count('<div class="table"><table>') == 7 and "overflow-x: auto" in html
    for row in dom["online"]["rows"] + dom["offline_naive"]["rows"]:
        for agent, c in row["cells"].items():
            assert c["std"] == pytest.approx(np.std(c["scores"], ddof=1))  # the sample std
            text = number = f"{c['mean']:.1f} ± {c['std']:.1f}"
            html_text = f"<b>{number}</b>" if c["bold"] else f">{number}<"
            if agent in row["paper"]:  # beside the paper's number: which conditions it misses
                assert not c["comparable"]
                label = f"(not comparable: {', '.join(c['missing'])})"
                text += f" {label}"  # Markdown: on the same line; HTML: on a line under it
                html_text = html_text.rstrip("<") + f'<br><span class="note">{label}</span>'
            assert (f"| **{text}** |" if c["bold"] else f"| {text} |") in md, (agent, text)
            assert html_text in html, html_text
    # a '|' in a name is escaped in Markdown, '<' and '&' in HTML
    assert "tests.train.fake\\|agent" in md and "fake|agent" in html
    table_lines = [line for line in md.splitlines() if "| " in line]
    assert all(line.startswith("|") and line.endswith("|") for line in table_lines)
    agg = dom["aggregates"]
    for split, tasks in (("online", 1), ("offline", 2)):
        label = render.AGGREGATE_SPLITS[split]
        for agent, e in agg[split]["agents"].items():
            name = agent.replace("|", chr(92) + "|")
            assert f"| {label} | {name} | {tasks} | {e['mean']:.1f} |" in md


def test_html_escapes_what_it_shows(tmp_path):
    pytest.importorskip("jinja2")
    recs = records(["test/<script>alert(1)</script>&"], ["bc"])
    write_report(write_sweep(tmp_path / "s", recs), tmp_path / "r", figures=False)
    html = (tmp_path / "r" / "report.html").read_text()
    assert "<script>" not in html and "&lt;script&gt;alert(1)&lt;/script&gt;&amp;" in html


def _layout_problems(fig):
    """Titles and legends outside the figure or overlapping each other or the axes' titles."""
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    W, H = fig.bbox.width, fig.bbox.height
    boxes = {"suptitle": fig._suptitle.get_window_extent(r)}
    for i, leg in enumerate(fig.legends):
        boxes[f"legend{i}"] = leg.get_window_extent(r)
    for i, ax in enumerate(fig.axes):
        if ax.get_title():
            boxes[f"title{i}"] = ax.title.get_window_extent(r)
        if ax.axison:
            boxes[f"axes{i}"] = ax.get_tightbbox(r)
    problems = [
        f"{k} outside the figure: {b.bounds}"
        for k, b in boxes.items()
        if b.x0 < -0.5 or b.y0 < -0.5 or b.x1 > W + 0.5 or b.y1 > H + 0.5
    ]
    names = list(boxes)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            if {a, b} == {a.replace("axes", "title"), a.replace("title", "axes")}:
                continue  # an axes' tight box holds its own title
            if boxes[a].overlaps(boxes[b]):
                problems.append(f"{a} overlaps {b}")
    return problems


@pytest.mark.parametrize(
    "tasks,agents",
    [
        (CONTROL[:1], ["bc"]),  # the one-task sweep whose title was cut at both edges
        (CONTROL[:1], ["bc", "d4pg", "bcq", "crr"]),
        (["test/a_task_name_that_is_quite_long_for_a_title"], ["tests.train.fake_agent"]),
        (CONTROL, ["bc", "d4pg"]),
        ([t for t in CONTROL] + ["control_suite/cheetah_run", "control_suite/humanoid_run"],
         ["bc", "d4pg", "bcq", "brac", "rabm"]),
    ],
)  # fmt: skip
def test_task_figures_keep_title_and_legend_inside_and_apart(tasks, agents):
    pytest.importorskip("matplotlib")
    from rlu.report.render import pyplot, tasks_figure

    plt = pyplot()
    rep = build_report(records(tasks, agents), reps=50)
    for domain, dom in rep["domains"].items():
        dom["dataset_p90"] = {t: 500.0 for t in dom["tasks"]}  # the dashed line and its legend
        fig = tasks_figure(dom, domain, plt)
        try:
            assert fig.legends, "no legend"
            assert _layout_problems(fig) == []
        finally:
            plt.close(fig)


def test_quickstart_figure_shows_policies_beside_the_data():
    pytest.importorskip("matplotlib")
    from rlu.report.render import pyplot, quickstart_figure

    plt = pyplot()
    pol = [{"policy": p, "mean": m, "std": 10.0, "returns": [m - 10, m + 10]}
           for p, m in (("random", 30.0), ("bc", 300.0), ("d4pg", 500.0))]  # fmt: skip
    fig = quickstart_figure(pol, np.linspace(100, 700, 40), "cartpole_swingup", plt)
    try:
        bars, hist = fig.axes
        assert [t.get_text() for t in bars.get_xticklabels()] == ["random", "bc", "d4pg"]
        assert [p.get_height() for p in bars.patches[:3]] == [30.0, 300.0, 500.0]
        assert sum(p.get_width() for p in hist.patches) == 40  # every dataset episode counted
        assert _layout_problems(fig) == []
    finally:
        plt.close(fig)


# --- the HTML in a real browser -----------------------------------------------------------------
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--hide-scrollbars",
]  # fmt: skip


def screenshot(html: Path, out: Path, profile: Path, size=(1200, 1600)) -> np.ndarray:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("no chromium (scripts/test.sh installs Debian's: apt-get install -y chromium)")
    profile.mkdir()
    cmd = [exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
           f"--screenshot={out}", html.resolve().as_uri()]  # fmt: skip
    env = {**os.environ, "HOME": str(profile)}
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    assert run.returncode == 0 and out.exists(), run.stderr[-2000:]
    from PIL import Image

    return np.asarray(Image.open(out).convert("RGB"))


def _rows_with_run(img: np.ndarray, color, min_run: int) -> int:
    """Pixel rows holding a horizontal run of at least ``min_run`` pixels of ``color``."""
    match = np.all(np.abs(img.astype(int) - color) <= 6, axis=2)
    count = 0
    for row in match:
        edges = np.diff(np.concatenate([[0], row.astype(np.int8), [0]]))
        starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        count += bool(len(starts) and (stops - starts).max() >= min_run)
    return count


@pytest.mark.slow
def test_report_html_in_headless_chromium(tmp_path):
    """Renders report.html in Debian's chromium and reads the screenshot: not blank, the tables'
    borders and header rows drawn, the figure loaded (its bars' colours on screen)."""
    pytest.importorskip("matplotlib")
    pytest.importorskip("PIL")
    sweep = write_sweep(tmp_path / "s", records(CONTROL, ["bc", "d4pg", "bcq"]))
    paths = write_report(sweep, tmp_path / "r")
    img = screenshot(tmp_path / "r" / "report.html", tmp_path / "shot.png", tmp_path / "profile",
                     size=(1200, 5000))  # fmt: skip
    assert img.shape == (5000, 1200, 3)
    ink = np.any(img < 200, axis=2).mean()
    assert 0.02 < ink < 0.6, f"{ink:.3f} of the page is ink: blank or unstyled"
    # table borders (#bbb) as long horizontal lines: the tables, a line per row edge
    assert _rows_with_run(img, (187, 187, 187), 300) >= 10
    assert _rows_with_run(img, (242, 242, 242), 100) >= 40  # header rows (3 x ~25 px)
    # the PNG is on screen: matplotlib's first colours fill the bars
    for color in ((31, 119, 180), (255, 127, 14), (44, 160, 44)):
        assert np.all(np.abs(img.astype(int) - color) <= 8, axis=2).sum() > 2000, color
    # and the page without its figures draws no bar colour (the check above can fail)
    for png in (tmp_path / "r" / "figures").iterdir():
        png.unlink()
    img2 = screenshot(tmp_path / "r" / "report.html", tmp_path / "shot2.png", tmp_path / "p2",
                      size=(1200, 5000))  # fmt: skip
    assert np.all(np.abs(img2.astype(int) - (31, 119, 180)) <= 8, axis=2).sum() < 50
    # the per-task bars, the performance profiles, the probability of improvement
    assert len(paths) == 6


def test_a_new_panel_is_one_function_and_one_renderer(tmp_path, monkeypatch):
    """What the paper's Atari/control panels will do: data in numbers.PANELS, blocks in
    render.RENDERERS; report.json, report.md and report.html pick it up."""
    pytest.importorskip("jinja2")
    from rlu.report import numbers, render

    def best_agent(ctx):
        return {"tasks": len(ctx.tasks), "agents": list(ctx.agents)}

    def render_best(dom, domain, figures):
        d = dom["best_agent"]
        rows = tuple(
            (render.Cell(a, numeric=False), render.Cell(str(d["tasks"]))) for a in d["agents"]
        )
        return [render.Text("Agents over tasks."), render.Table(("agent", "tasks"), rows)]

    monkeypatch.setitem(numbers.PANELS, "best_agent", best_agent)
    monkeypatch.setitem(render.RENDERERS, "best_agent", render_best)
    write_report(write_sweep(tmp_path / "s", records(CONTROL, ["bc", "crr"])), tmp_path / "r",
                 figures=False)  # fmt: skip
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    assert rep["domains"]["control_suite"]["best_agent"] == {"tasks": 3, "agents": ["bc", "crr"]}
    assert rep["domains"]["control_suite"]["panels"][-1] == "best_agent"
    md = (tmp_path / "r" / "report.md").read_text()
    assert "Agents over tasks.\n\n| agent | tasks |\n|---|---|\n| bc | 3 |\n| crr | 3 |" in md
    assert (
        '<td class="label">crr</td><td class="num">3</td>'
        in (tmp_path / "r" / "report.html").read_text()
    )


def test_cells_of_fewer_seeds_say_how_many(tmp_path):
    pytest.importorskip("jinja2")
    recs = records(CONTROL[:1], ["bc", "d4pg"])  # three seeds each...
    recs = [r for r in recs if not (r["agent"] == "d4pg" and r["seed"] > 0)]  # ...d4pg one
    recs += [{**r, "agent": "brac"} for r in recs if r["agent"] == "bc" and r["seed"] < 2]
    # a second task without brac: its row keeps every column in place
    recs += [{**r, "task": CONTROL[1]} for r in recs if r["agent"] != "brac"]
    write_report(write_sweep(tmp_path / "s", recs), tmp_path / "r", figures=False)
    table = [line for line in (tmp_path / "r" / "report.md").read_text().splitlines()
             if line.startswith("| control_suite/")][:2]  # fmt: skip
    assert [line.count(" | ") for line in table] == [6, 6]  # task, 3 x (ours, the paper's)
    # walker walk: bc's paper cell, no brac of ours, then the paper's brac all the same
    assert "| 380.0 ± 32.0 |  | 786.0 ± 294.0 |" in table[1]
    assert "seeds" not in table[0].split(" | ")[1]  # bc's 3 seeds meet rlu's 3
    cells = json.loads((tmp_path / "r" / "report.json").read_text())["domains"]["control_suite"]
    cells = cells["online"]["rows"][0]["cells"]
    md = (tmp_path / "r" / "report.md").read_text().replace("**", "")  # bold or not
    bc, brac, d4pg = cells["bc"], cells["brac"], cells["d4pg"]
    assert f"{bc['mean']:.1f} ± {bc['std']:.1f} (not comparable:" in md  # all the seeds
    assert f"{brac['mean']:.1f} ± {brac['std']:.1f} (2 seeds) (not comparable:" in md
    # one seed: its mean, no spread (not a ± 0.0), and "seeds" among what it misses
    assert d4pg["std"] is None and d4pg["mean"] == d4pg["scores"][0]
    assert f"{d4pg['mean']:.1f} (1 seed) (not comparable: " in md
    assert f"{d4pg['mean']:.1f} ± " not in md
    assert "seeds" in d4pg["missing"] and "seeds" in brac["missing"]
    assert "seeds" not in bc["missing"]


def _with_curves(recs, seed=0):
    """Records as runs read back: each with its evaluations (three of them, the last one its
    score), as ``rlu.training.runs.learning_curve`` gives them."""
    rng = np.random.default_rng(seed)
    out = []
    for r in recs:
        means = [*rng.uniform(0, r["score"], 2), r["score"]]
        out.append({**r, "curve": [{"step": 100 * (i + 1), "mean": float(m), "episodes": 2}
                                   for i, m in enumerate(means)]})  # fmt: skip
    return out


@pytest.mark.parametrize("agents", [["bc"], ["bc", "d4pg", "bcq"]])
def test_curves_profiles_and_improvement_figures_are_labelled_and_fit(agents):
    """The learning curves (seeds thin, mean thick, its band ± sample std), the performance
    profiles and the probability of improvement: titles that name what is drawn and how the
    band or interval is made, axes labelled, legends inside the figure and apart."""
    pytest.importorskip("matplotlib")
    from rlu.report.render import (
        curves_figure,
        improvement_figure,
        profiles_figure,
        pyplot,
    )

    plt = pyplot()
    rep = build_report(_with_curves(records(CONTROL, agents)), reps=50)
    dom = rep["domains"]["control_suite"]
    fig = curves_figure(dom, "control_suite", plt)
    try:
        assert _layout_problems(fig) == []
        title = fig._suptitle.get_text().replace("\n", " ")
        assert "learning curves" in title and "band: ± sample std (ddof 1) over seeds" in title
        drawn = [ax for ax in fig.axes if ax.axison]
        assert [ax.get_title() for ax in drawn] == ["cartpole_swingup", "fish_swim", "walker_walk"]
        assert all(ax.get_xlabel() == "learner steps" for ax in drawn)
        # per agent: 3 seed lines and the mean; the mean is the seeds' mean
        (t0,) = [t for t in dom["curves"]["tasks"] if t["task"] == CONTROL[0]]
        c = t0["agents"]["bc"]
        assert c["mean"] == pytest.approx(np.mean([s["means"] for s in c["seeds"]], axis=0))
        assert c["std"] == pytest.approx(np.std([s["means"] for s in c["seeds"]], axis=0, ddof=1))
        assert len(drawn[0].lines) == 4 * len(agents)
        labels = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
        assert "one seed" in labels and "bc (3 seeds)" in labels
    finally:
        plt.close(fig)
    if len(agents) < 2:
        assert "improvement" in dom["absent"]  # no pair of agents to compare
    for make, name, words in (
        (profiles_figure, "profiles", "Performance profiles"),
        (improvement_figure, "improvement", "Probability of improvement"),
    ):
        if name not in dom:
            continue
        fig = make(dom, plt)
        try:
            assert _layout_problems(fig) == []
            title = fig._suptitle.get_text().replace("\n", " ")
            assert words in title and "95 % stratified bootstrap CI over seeds" in title
            axes = [ax for ax in fig.axes if ax.axison]
            assert [ax.get_title().split(":")[0] for ax in axes] == [
                "online policy selection, online-selection tasks",
                "naive offline selection, offline-selection tasks",
            ]
            assert all(ax.get_xlabel() for ax in axes)
        finally:
            plt.close(fig)  # fmt: skip


def test_profiles_and_probability_of_improvement_are_rliables_number_for_number():
    """rlu computes rliable's performance profiles and probability of improvement vectorised
    (bench/report_profiles.py: ~100x rliable's per-replicate Python); the same resamples from
    the same generator give the same numbers, intervals included."""
    rly = pytest.importorskip("rliable.library")
    metrics = pytest.importorskip("rliable.metrics")
    from rlu.report.profiles import performance_profile, probability_of_improvement

    rng = np.random.default_rng(3)
    scores = {"a": rng.integers(0, 6, (3, 4)).astype(float),  # ties, within and across agents
              "b": rng.normal(3, 2, (5, 4)), "c": rng.normal(3, 2, (1, 4))}  # fmt: skip
    taus = np.linspace(-1, 7, 17)
    np.random.seed(0)
    want, want_ci = rly.create_performance_profile(scores, taus, reps=120)
    got, got_ci = performance_profile(scores, taus, reps=120, random_state=0)
    for k in scores:
        assert np.array_equal(got[k], want[k]) and np.array_equal(got_ci[k], want_ci[k]), k
    pairs = {"a,b": (scores["a"], scores["b"]), "b,c": (scores["b"], scores["c"]),
             "a,a": (scores["a"], scores["a"])}  # fmt: skip
    np.random.seed(0)
    want, want_ci = rly.get_interval_estimates(
        {k: list(v) for k, v in pairs.items()}, metrics.probability_of_improvement, reps=120
    )
    got, got_ci = probability_of_improvement(pairs, reps=120, random_state=0)
    for k in pairs:
        assert got[k] == pytest.approx(float(want[k]), abs=1e-12), k
        assert np.allclose(got_ci[k], np.ravel(want_ci[k]), rtol=0, atol=1e-12), k
    assert got["a,a"] == 0.5  # an agent against itself: ties count half
