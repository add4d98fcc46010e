"""``rlu report RUN_OR_SWEEP ...``: the paper's tables and figures, learning curves and rliable's
aggregate views of any runs (``rlu train`` run folders, sweeps, or a mix), as Markdown, HTML,
PNG and JSON (the numbers the tables print).

Three parts: this module reads the inputs and writes the files, ``numbers`` computes every
number (a pure function of the runs' records, one dict, written as report.json) and ``render``
lays them out (Markdown and HTML through Jinja2 templates, PNG through matplotlib). A new panel
is one function in ``numbers.PANELS`` and one renderer in ``render.RENDERERS``.

Inputs. A run folder is read from what it recorded (``rlu.training.runs.run_record``: result.json,
config.json, eval.jsonl), a sweep from its results.jsonl (and each run's eval.jsonl for the
curves). Runs are grouped by task, agent, configuration (the label of their overrides) and
seed. Runs of the same label that differ in what produced them (preset, learner steps, data,
evaluation episodes) are told apart by a label suffix naming the difference; a run given twice
(alone and in its sweep) counts once. Refused, saying why: a folder that is neither a run nor a
sweep, a run still training, and two different runs of the same task, agent, configuration,
seed and settings (the report would have to drop one).

Outputs. Everything is written through ``rlu.files`` (temporaries renamed into place; figures
through ``atomic_path(..., suffix=True)``), into a report folder made by ``make_folder`` and
checked before any work (:func:`check_report_output`): never an input, a folder inside one or
holding one (a dataset, a sweep, a run, its checkpoints), never ``''``, never a folder holding
anything but an earlier report of rlu's (report.json written by ``rlu report``).
"""

from __future__ import annotations

import json
import os
import sys
import types
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from rlu import files
from rlu.report.conditions import CONDITIONS, PaperPreset, paper_conditions
from rlu.report.numbers import (
    DATA_SOURCES,
    PANELS,
    Absent,
    DomainContext,
    PaperPresets,
    build_report,
    dataset_percentile,
    load_paper_results,
    paper_entry,
    report_key,
    run_provenance,
    sample_std,
    task_info,
)
from rlu.training import runs
from rlu.types import RluError

__all__ = [
    "CONDITIONS",
    "DATA_SOURCES",
    "PANELS",
    "Absent",
    "DomainContext",
    "PaperPreset",
    "PaperPresets",
    "build_report",
    "check_report_output",
    "dataset_percentile",
    "load_paper_results",
    "paper_conditions",
    "paper_entry",
    "read_inputs",
    "run_provenance",
    "sample_std",
    "task_info",
    "write_report",
]

Paths = str | os.PathLike | Sequence[str | os.PathLike]


def _items(paths: Paths) -> list[Path]:
    items = [Path(paths)] if isinstance(paths, str | os.PathLike) else [Path(p) for p in paths]
    if not items:
        raise RluError("nothing to report: give one or more run or sweep folders")
    for p in items:
        if not runs.is_run(p) and not runs.is_sweep(p):
            what = "does not exist" if not p.exists() else "is neither"
            raise RluError(
                f"{p} {what} a run folder (config.json, from rlu train --out) nor a sweep "
                "folder (sweep.json or results.jsonl, from rlu sweep --out); give those"
                if what == "is neither"
                else f"{p} does not exist; give run folders (rlu train --out) or sweep folders "
                "(rlu sweep --out)"
            )
    return items


def _inputs_of(item: Path) -> list[str]:
    """What a report of ``item`` reads: the folder, its runs' folders and their datasets."""
    found = [str(item)]
    if runs.is_sweep(item):
        if (item / runs.SWEEP_CONFIG).is_file():
            found += list(runs.load_sweep_config(item)["datasets"].values())
        if (item / runs.RESULTS).is_file():
            found += [r["run"] for r in runs.load_results(item)]
    else:
        facts = files.read_json(item / runs.CONFIG, runs.RUN_FACTS, runs.FIX_RUN)
        found.append(facts["dataset"]["path"])
    return found


def _ours(folder: Path) -> bool:
    """Whether ``folder``'s report.json was written by ``rlu report`` (or is one from before
    reports carried their writer: a JSON object holding ``domains`` only)."""
    try:
        data = files.read_json(folder / runs.REPORT, fix="")
    except RluError:
        return False
    return isinstance(data, Mapping) and (
        data.get("written_by") == runs.REPORT_WRITER or set(data) == {"domains"}
    )


def check_report_output(paths: Paths, out: str | os.PathLike | None) -> Path:
    """The report folder of ``paths`` (``out``, or FOLDER/report for one input folder),
    refused before any work when it is ``''``, an input or inside one or holding one (a
    dataset, a sweep, a run folder or its checkpoints), or an existing folder that holds
    anything but an earlier report of rlu's. An input's own ``report`` subfolder is its
    report's place: inside that input, but inside nothing else."""
    items = _items(paths)
    if out is None:
        if len(items) > 1:
            raise RluError(f"{len(items)} folders to report: pass --out for the report folder")
        out = items[0] / "report"
    if not str(out).strip():
        raise RluError("--out is empty; give the report folder's path")
    out = Path(out)
    inputs: list[str] = []
    for item in items:
        own = Path(os.path.realpath(out)) == Path(os.path.realpath(item / "report"))
        inputs += [p for p in _inputs_of(item) if not (own and p == str(item))]
    files.check_output(out, inputs, runs.REPORT, "report folder", "--out")
    if (out / runs.REPORT).exists() and not _ours(out):
        raise RluError(
            f"--out {out} holds a {runs.REPORT} that rlu report did not write; rlu replaces only "
            "its own reports: choose a new --out or empty that folder yourself"
        )
    return out


def read_inputs(
    paths: Paths,
) -> tuple[list[dict[str, Any]], dict[str, list[str]], dict[str, Any] | None]:
    """(records, datasets by report task, FQE selections) of run and sweep folders: each run's
    record with its learning curve (``curve``) and its report task (``report_key``)."""
    records: dict[tuple[str, str, str, int], dict[str, Any]] = {}
    where: dict[tuple[str, str, str, int], str] = {}
    datasets: dict[str, list[str]] = {}
    selections: list[dict[str, Any]] = []
    any_fqe = False
    found: list[tuple[dict[str, Any], str]] = []
    for item in _items(paths):
        if runs.is_sweep(item):
            sweep_datasets = (
                runs.load_sweep_config(item)["datasets"]
                if (item / runs.SWEEP_CONFIG).is_file()
                else {}
            )
            for r in runs.load_results(item):
                r = dict(r)
                if r["task"] in sweep_datasets:
                    r.setdefault("dataset", sweep_datasets[r["task"]])
                found.append((r, f"{item / runs.RESULTS}"))
            if (item / runs.FQE).is_file():
                any_fqe = True
                selections += runs.read_fqe(item)["selections"]
        else:
            found.append((runs.run_record(item), str(item)))
    for r, source in _told_apart(found):
        r = {**r, "task": report_key(r)}
        key = (r["task"], r["agent"], r["config"], int(r["seed"]))
        if key in records and os.path.realpath(r["run"]) == os.path.realpath(where[key]):
            continue  # a run given alone and in its sweep
        if key in records:
            raise RluError(
                f"{source}: run {r['run']} is {_key_text(key)}, and so is {where[key]}, with the "
                "same settings; a report holds one run of each: leave one of them out"
            )
        records[key], where[key] = {**r, "curve": runs.learning_curve(r["run"])}, r["run"]
        if r.get("dataset"):
            paths_of = datasets.setdefault(r["task"], [])
            if r["dataset"] not in paths_of:
                paths_of.append(r["dataset"])
    fqe = {"selections": selections} if any_fqe else None
    return list(records.values()), datasets, fqe


def _key_text(key: tuple[str, str, str, int]) -> str:
    task, agent, config, seed = key
    return f"{task} {agent} {config} seed {seed}"


def _told_apart(
    found: Sequence[tuple[dict[str, Any], str]],
) -> list[tuple[dict[str, Any], str]]:
    """The records with the configuration label of runs that share one but not what produced
    them (preset, learner steps, evaluation episodes, data) suffixed with what differs, so that
    each is its own configuration."""
    groups: dict[tuple[str, str, str], set[str]] = {}
    for r, _ in found:
        groups.setdefault((report_key(r), r["agent"], r["config"]), set()).add(_made(r))
    out = []
    for r, source in found:
        made = groups[(report_key(r), r["agent"], r["config"])]
        if len(made) > 1:
            p = run_provenance(r)
            fields = {
                "preset": f"preset {p['preset']}",
                "steps": f"{p['steps']} steps",
                "eval_episodes": f"{p['eval_episodes']} episodes",
                "data": f"{p['data']['source']} data",
            }
            fields["pretrain_steps"] = f"{p['pretrain_steps']} pre-training steps"
            named = ", ".join(fields[k] for k in _differing(made))
            r = {**r, "config": f"{r['config']} ({named})"}
        out.append((r, source))
    return out


def _made(r: Mapping[str, Any]) -> str:
    return json.dumps(run_provenance(r), sort_keys=True)


def _differing(made: set[str]) -> list[str]:
    entries = [json.loads(m) for m in made]
    keys = ("preset", "steps", "eval_episodes", "data")
    out = [k for k in keys if len({json.dumps(e[k], sort_keys=True) for e in entries}) > 1]
    return out or ["pretrain_steps"]


def write_report(
    paths: Paths,
    out: str | os.PathLike | None = None,
    random_scores: Mapping[str, float] | None = None,
    best_behaviour: Mapping[str, float] | None = None,
    figures: bool = True,
    paper: PaperPresets | None = None,
) -> list[Path]:
    """Write report.md, report.html, report.json and figures/*.png of run and sweep folders
    (any mix, reported together); return their paths. ``out`` is the report folder (default
    FOLDER/report for one folder; required with several), checked before anything is read
    further (:func:`check_report_output`). ``paper(agent, discrete)`` is what the report checks
    of an agent's paper preset (:func:`report` passes ``rlu.report.conditions.paper_preset``,
    which reads the agent modules); without it no cell is comparable with the paper's numbers."""
    from rlu.report import render

    out = check_report_output(paths, out)
    records, datasets, fqe = read_inputs(paths)
    rep = build_report(records, datasets, random_scores, best_behaviour, fqe=fqe, paper=paper)
    files.check_targets(out, REPORT_FILES)  # every file to replace, before the first is
    files.make_folder(out)
    old = _previous_figures(out)
    parts = render.sections(rep, render.Figures(out) if figures else None)
    images = [b.path for s in parts for b in s.blocks if isinstance(b, render.Image)]
    paths_out = [out / "report.md", out / "report.html", out / runs.REPORT]
    files.write_atomic(paths_out[0], render.render("report.md.j2", "rlu report", parts), out)
    files.write_atomic(paths_out[1], render.render("report.html.j2", "rlu report", parts), out)
    inputs = [str(p) for p in _items(paths)]
    files.write_json(
        paths_out[2],
        {"written_by": runs.REPORT_WRITER, "inputs": inputs, "figures": images, **rep},
        root=out,
    )
    for rel in old - set(images):  # figures of an earlier report that this one does not draw
        stale = out / rel
        if stale.is_file() and not stale.is_symlink():
            stale.unlink()
    return paths_out + [out / p for p in images]


REPORT_FILES = ("report.md", "report.html", runs.REPORT, "figures/*.png")
"""What a report folder holds (and a new report replaces)."""


def _previous_figures(out: Path) -> set[str]:
    """The figures an earlier report in ``out`` listed (only those are ever removed)."""
    if not (out / runs.REPORT).is_file():
        return set()
    try:
        data = files.read_json(out / runs.REPORT, fix="")
    except RluError:
        return set()
    listed = data.get("figures") if isinstance(data, Mapping) else None
    return {
        f
        for f in listed or []
        if isinstance(f, str)
        and f.startswith("figures/")
        and f.count("/") == 1
        and f.endswith(".png")
    }


def report(
    paths: Any,
    out: str | os.PathLike | None = None,
    fqe_steps: int | None = None,
    device: Any = "cpu",
    figures: bool = True,
) -> list[Path]:
    """Report run folders (``rlu train --out``) and sweep folders (``rlu sweep --out``), any
    mix, together (``rlu.report.write_report``); returns the files written.
    ``fqe_steps``: first run offline selection by FQE over every sweep (``SWEEP/fqe.json``)
    with that many FQE steps. ``rlu.report(paths)`` is this function."""
    from rlu.report.conditions import paper_preset
    from rlu.training.restore import fqe_selection

    items = [paths] if isinstance(paths, str | os.PathLike) else list(paths)
    check_report_output(items, out)  # before FQE: nothing is computed for a refused folder
    if fqe_steps is not None:
        from rlu.evaluation.fqe import FQEConfig

        for item in items:
            if runs.is_sweep(item):
                fqe_selection(item, FQEConfig(steps=fqe_steps), device)
    return write_report(items, out, figures=figures, paper=paper_preset)


class _CallableModule(types.ModuleType):
    """``rlu.report(paths)`` calls :func:`report` also once this package is imported (the
    import binds the name ``rlu.report`` to the package)."""

    def __call__(self, *args: Any, **kwargs: Any) -> list[Path]:
        return report(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
