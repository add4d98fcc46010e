"""``rlu list``, ``rlu agents`` and ``rlu info TASK|PATH``."""

from __future__ import annotations

import argparse
import json
import os
import re
from typing import TYPE_CHECKING

from rlu.types import RluError

if TYPE_CHECKING:
    from rlu.tasks import TaskRef


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("list", help="list every task of the suite")
    from rlu.domains import DOMAINS

    p.add_argument("--domain", help=", ".join(DOMAINS))
    p.add_argument("--selection", choices=["online", "offline"])
    p.add_argument("--json", action="store_true", help="print a JSON array")
    p.set_defaults(func=_list)

    p = sub.add_parser("agents", help="list every agent (the names --agent and --agents take)")
    p.add_argument("--json", action="store_true", help="print a JSON array")
    p.set_defaults(func=_agents)

    p = sub.add_parser("info", help="describe a task id or a dataset directory")
    p.add_argument("target", help="a task id (control_suite/cartpole_swingup) or a dataset path")
    p.add_argument(
        "--json", action="store_true", help="print JSON (for a dataset: every episode's return too)"
    )
    p.set_defaults(func=_info)


def _list(args: argparse.Namespace) -> int:
    from rlu.tasks import list_tasks

    tasks = list_tasks(args.domain, args.selection)
    if args.json:
        print(json.dumps([t.to_json() for t in tasks], indent=1))
        return 0
    rows = [("id", "domain", "selection", "actions", "ep.len", "datasets")]
    for t in tasks:
        kind = f"{t.action_dim} discrete" if t.discrete else f"{t.action_dim} cont."
        rows.append(
            (t.id, t.domain, t.selection, kind, str(t.episode_length), str(len(t.datasets)))
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for r in rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip())
    print(f"{len(tasks)} tasks")
    from rlu.domains import DOMAINS

    for name in dict.fromkeys(t.domain for t in tasks):  # in the table's order
        if DOMAINS[name].data_only:
            print(f"{name}: data only, no env ({DOMAINS[name].data_only})")
    return 0


def _agents(args: argparse.Namespace) -> int:
    """The registry (``rlu.agents.AGENTS``), each agent's summary read from its module's
    docstring without importing it (no torch needed to list them)."""
    from rlu.agents import AGENTS

    rows = [
        {"name": name, "actions": "discrete" if discrete else "continuous", "module": module,
         "summary": _summary(module)}
        for (name, discrete), module in AGENTS.items()
    ]  # fmt: skip
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    table = [("name", "actions", "summary")] + [
        (r["name"], r["actions"], r["summary"]) for r in rows
    ]
    widths = [max(len(r[i]) for r in table) for i in range(2)]
    for r in table:
        print(f"{r[0].ljust(widths[0])}  {r[1].ljust(widths[1])}  {r[2]}".rstrip())
    print(f"{len(rows)} agents; rlu train --agent NAME (docs/agents.md: adding one)")
    return 0


def _summary(module: str) -> str:
    """The first sentence of a module's docstring, read from its source."""
    import ast
    import importlib.util

    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        return ""
    with open(spec.origin, encoding="utf-8") as fh:
        doc = ast.get_docstring(ast.parse(fh.read())) or ""
    text = " ".join(doc.split("\n\n")[0].split())
    first = re.split(r"(?<!\bal)\.\s", text)[0].rstrip(".")  # "et al." ends no sentence
    return first if len(first) <= 100 else first[:97].rstrip() + "..."


def _info(args: argparse.Namespace) -> int:
    if os.path.isdir(args.target):
        from rlu.data.store import open_dataset

        ds = open_dataset(args.target, verify=False)
        info = ds.info()
        if args.json:  # every whole episode's return, in order (too long for the tree print)
            info["returns"]["per_episode"] = ds.episode_returns().tolist()
    else:
        from rlu.tasks import DOMAINS, resolve_task

        target = args.target
        if os.path.exists(target) or target.startswith((".", "~", os.sep)):  # a path
            what = "is a file, not" if os.path.exists(target) else "is neither a task id nor"
            raise RluError(
                f"{target} {what} a dataset directory; pass a dataset folder (the one holding "
                "manifest.json) or a task id such as control_suite/cartpole_swingup (rlu list)"
            )
        try:
            ref = resolve_task(target)
            info = ref.task.to_json()
        except RluError as e:
            tfds = target.startswith("rlu_")
            if os.sep in target and target.split(os.sep)[0] not in DOMAINS and not tfds:
                raise RluError(
                    f"{e} Nor is {target} a dataset directory (no such folder)."
                ) from None
            raise
        if not args.json:
            info = _readable_task(info, ref)
    if args.json:
        print(json.dumps(info, indent=1))
    else:
        _print_tree(info)
    return 0


def _readable_task(info: dict, ref: TaskRef) -> dict:
    """The task's JSON for reading: a task with one dataset has its counts without the ``""``
    key that stands for it in JSON (``episodes: 40``, not ``episodes: {"": 40}``); a TFDS name
    says what it names."""
    out = {}
    if ref.name != ref.task.id:
        picks = {"family": ref.family, "run": ref.run, "challenge": ref.challenge}
        picks["size"] = ref.size
        chosen = ", ".join(f"{k} {v}" for k, v in picks.items() if v is not None)
        out["alias"] = f"{ref.name} = {ref.task.id}" + (f" ({chosen})" if chosen else "")
    single = list(info["datasets"]) == [""]
    for k, v in info.items():
        if k == "datasets" and single:
            continue  # one dataset, unnamed
        if k == "episodes":
            if single:
                v = v[""]
            elif not v:
                v = "not a paper number (episodes vary per run)"
        if k == "release" and single:
            v = [{**r, "shards": r["shards"][""]} for r in v]
        out[k] = v
    from rlu.domains import DOMAINS

    if DOMAINS[ref.task.domain].data_only:
        out["data_only"] = f"no env: {DOMAINS[ref.task.domain].data_only}"
    return out


def _print_tree(d: object, indent: int = 0) -> None:
    pad = "  " * indent
    if isinstance(d, dict):
        for k, v in d.items():
            if isinstance(v, (dict, list)) and v and not _flat(v):
                print(f"{pad}{k}:")
                _print_tree(v, indent + 1)
            else:
                print(f"{pad}{k}: {json.dumps(v)}")
    elif isinstance(d, list):
        for v in d:
            if isinstance(v, (dict, list)):
                print(f"{pad}-")
                _print_tree(v, indent + 1)
            else:
                print(f"{pad}- {v}")


def _flat(v: object) -> bool:
    if isinstance(v, dict):
        return all(not isinstance(x, (dict, list)) for x in v.values()) and len(v) <= 4
    if isinstance(v, list):
        return all(not isinstance(x, (dict, list)) for x in v)
    return True
