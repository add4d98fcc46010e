"""MkDocs hooks of the rlu site (``hooks:`` in mkdocs.yml): pages made from rlu's registries.

The site is built from what the code holds, so it cannot fall behind it:

- one page per registered agent module (``rlu.agents.AGENTS``; a module registered for both
  action types, ``dt``, gets one page), ``agents/<module>.md``: the module
  docstring, the rows of docs/paper_settings.md that name the agent, its ``Config`` (paper
  defaults, a docstring per field), ``PRESETS`` and ``GRID`` as written in the agent file, and
  its ``Agent`` class; the pages go into the nav under "Agents";
- ``<!-- rlu:tasks DOMAIN -->`` in a page becomes the table of that domain's tasks
  (``rlu.tasks``);
- ``<!-- rlu:cli -->`` becomes every ``rlu`` command's ``--help``, from ``rlu.cli``'s parser.

Only ``rlu.agents`` (its registry, not an agent), ``rlu.tasks`` and ``rlu.cli`` are imported:
numpy, no torch. Agent files are read as text (``ast``), never imported. The functions that make
the Markdown take plain arguments, so tests/docs/test_site.py checks them without MkDocs.
"""

from __future__ import annotations

import argparse
import ast
import os
import re
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # the checkout's rlu, also when mkdocs runs from another venv
    sys.path.insert(0, str(ROOT))

AGENTS_NAV_TITLE = "Agents"
PAPER_SETTINGS = "paper_settings.md"
# Which sections of docs/paper_settings.md hold the rows of a continuous / a discrete agent.
CONTINUOUS_SECTIONS = ("continuous",)
DISCRETE_SECTIONS = ("Atari baselines",)


# ---- agents -------------------------------------------------------------------------------


def agent_entries() -> list[dict[str, Any]]:
    """Every registered agent module: name, discrete (None for a module registered for both
    action types, listed once at its discrete entry), module, page path, nav title, in AGENTS
    order."""
    from rlu.agents import AGENTS

    out = []
    for (name, discrete), module in AGENTS.items():
        both = AGENTS.get((name, not discrete)) == module
        if both and not discrete:
            continue  # listed once, at its discrete entry
        stem = module.rsplit(".", 1)[-1]
        kind = (
            "continuous and discrete" if both else "discrete, Atari" if discrete else "continuous"
        )
        out.append(
            {
                "name": name,
                "discrete": None if both else discrete,
                "module": module,
                "file": ROOT / Path(*module.split(".")).with_suffix(".py"),
                "page": f"agents/{stem}.md",
                "title": f"{name} ({kind})",
            }
        )
    return out


def module_names(source: str) -> dict[str, Any]:
    """What an agent file binds: the classes ``Config`` / ``Agent`` alias, the source text
    of its ``PRESETS`` and ``GRID`` assignments, and under ``composed`` the settings classes of
    its own that the config's fields are typed with (dt's ``AtariDT``)."""
    tree = ast.parse(source)
    found: dict[str, Any] = {}
    classes = {node.name: node for node in tree.body if isinstance(node, ast.ClassDef)}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1:
            target, value = node.targets[0], node.value
        elif isinstance(node, ast.AnnAssign) and node.value is not None:
            target, value = node.target, node.value
        else:
            continue
        if not isinstance(target, ast.Name):
            continue
        if target.id in ("Config", "Agent") and isinstance(value, ast.Name):
            found[target.id] = value.id
        elif target.id in ("PRESETS", "GRID"):
            text = ast.get_source_segment(source, node) or ""
            found[target.id] = re.sub(r"\s*# fmt: skip", "", text)
    config = classes.get(found.get("Config", ""))
    fields = config.body if config is not None else []
    found["composed"] = [
        f.annotation.id
        for f in fields
        if isinstance(f, ast.AnnAssign) and isinstance(f.annotation, ast.Name)
        and f.annotation.id in classes
    ]  # fmt: skip
    return found


def slug(title: str) -> str:
    """The anchor Python-Markdown's toc extension gives a heading (its default slugify)."""
    from markdown.extensions.toc import slugify

    return slugify(title, "-")


def markdown_sections(text: str) -> list[tuple[str, str]]:
    """(``## heading``, body) pairs of a Markdown page."""
    parts = re.split(r"^## (.+)$", text, flags=re.M)
    return list(zip(parts[1::2], parts[2::2], strict=True))


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def paper_rows(text: str, name: str, discrete: bool) -> list[tuple[str, str, list[str]]]:
    """(section heading, table header line, the rows naming the agent) of paper_settings.md.

    A row names the agent when one of its cells holds the agent's name in capitals as a word
    (``BC``, ``D4PG``: the page writes agents so), searched in the sections of the agent's kind;
    a section whose prose names the agent in backticks (``dopamine_dqn``) gives all its rows."""
    wanted = (
        (*CONTINUOUS_SECTIONS, *DISCRETE_SECTIONS)
        if discrete is None
        else DISCRETE_SECTIONS
        if discrete
        else CONTINUOUS_SECTIONS
    )
    word = re.compile(rf"(?<![\w-]){re.escape(name.upper())}(?![\w-])")
    out = []
    for heading, body in markdown_sections(text):
        lines = body.splitlines()
        table = [i for i, line in enumerate(lines) if line.startswith("|")]
        if not table:
            continue
        header, rows = lines[table[0]], [lines[i] for i in table[2:]]
        prose = "\n".join(line for line in lines if not line.startswith("|"))
        if f"`{name}`" in prose:
            out.append((heading, header, rows))
        elif any(w in heading for w in wanted):
            picked = [r for r in rows if any(word.search(c) for c in _cells(r))]
            if picked:
                out.append((heading, header, picked))
    return out


def agents_table_row(text: str, name: str, file: str) -> dict[str, str] | None:
    """The agent's row of docs/agents.md's table (name, actions, file, source)."""
    for line in text.splitlines():
        if line.startswith("|"):
            cells = _cells(line)
            if len(cells) == 4 and cells[0] == f"`{name}`" and cells[2] == f"`{file}`":
                return dict(zip(("name", "actions", "file", "source"), cells, strict=True))
    return None


def agent_page(entry: dict[str, Any], settings: str, agents_md: str) -> str:
    """The Markdown of one agent's page."""
    name, module, discrete = entry["name"], entry["module"], entry["discrete"]
    source = entry["file"].read_text()
    names = module_names(source)
    missing = [k for k in ("Config", "Agent", "PRESETS", "GRID") if k not in names]
    if missing:
        raise ValueError(
            f"{entry['file']}: no module-level {', '.join(missing)}; every agent file binds "
            "Config, Agent, PRESETS and GRID (docs/agents.md)"
        )
    row = agents_table_row(agents_md, name, entry["file"].name)
    kind = {None: "continuous and discrete actions", True: "discrete actions, Atari",
            False: "continuous actions"}[discrete]  # fmt: skip
    task = {None: "continuous- or discrete-action (Atari)", True: "discrete-action (Atari)",
            False: "continuous-action"}[discrete]  # fmt: skip
    lines = [
        f"# `{name}` ({kind})",
        "",
        f"Module `{module}` (`{entry['file'].relative_to(ROOT)}`); "
        f"`rlu train --agent {name}` on a {task} task picks it.",
    ]
    if row is not None:
        lines += ["", f"Source: {row['source']}."]
    lines += ["", f"::: {module}", "    options:", "      members: false"]
    lines += ["      show_root_heading: false", ""]
    lines += ["## The paper's settings", ""]
    rows = paper_rows(settings, name, discrete)
    if rows:
        lines.append(
            f"The rows of [the paper's settings]({_rel(PAPER_SETTINGS)}) that name `{name}` "
            "(**=**: rlu's `paper` preset matches the paper):"
        )
        for heading, header, picked in rows:
            ncols = len(_cells(header))
            lines += [
                "",
                f"From [{heading}]({_rel(PAPER_SETTINGS)}#{slug(heading)}):",
                "",
                header,
                "|" + "---|" * ncols,
                *picked,
            ]
    else:
        lines.append(
            f"`{name}` is not one of the paper's baselines, so [the paper's settings]"
            f"({_rel(PAPER_SETTINGS)}) has no row for it; the module docstring above names the "
            "paper and the code its settings come from."
        )
    lines += [
        "",
        "## Config",
        "",
        f"`{names['Config']}`: the `paper` preset is `{names['Config']}()`. Override a field on "
        "the command line (`rlu train ... FIELD=VALUE`) or in Python "
        f"(`rlu.agents.make_config({name!r}, {bool(discrete)}, 'small', FIELD=VALUE)`).",
        "",
        *(
            [
                "The settings every Atari agent shares are its `atari` field: "
                "[`AtariSettings`][rlu.agents.discrete_common.AtariSettings].",
                "",
            ]
            if discrete
            else []
        ),
        f"::: {module}.{names['Config']}",
        "    options:",
        "      show_root_heading: true",
        "      heading_level: 3",
        "",
        *(
            line
            for composed in names["composed"]
            for line in (
                f"::: {module}.{composed}",
                "    options:",
                "      show_root_heading: true",
                "      heading_level: 3",
                "",
            )
        ),
        "## Presets and grid",
        "",
        f"As written in `{entry['file'].relative_to(ROOT)}` (`GRID` is the paper's "
        "hyper-parameter sweep, which `rlu sweep` expands):",
        "",
        "```python",
        names["PRESETS"],
        names["GRID"],
        "```",
        "",
        "## Agent",
        "",
        f"::: {module}.{names['Agent']}",
        "    options:",
        "      show_root_heading: true",
        "      heading_level: 3",
        "",
    ]
    return "\n".join(lines)


def _rel(page: str) -> str:
    """A link from a page under agents/ to a page at the docs root."""
    return f"../{page}"


# ---- tasks --------------------------------------------------------------------------------


def _spec_text(spec: Any) -> str:
    from rlu.types import BoundedSpec, DiscreteSpec

    if isinstance(spec, DiscreteSpec):
        return f"{spec.num_values} actions"
    if isinstance(spec, BoundedSpec):
        return f"{_shape(spec)} in [{spec.minimum:g}, {spec.maximum:g}]"
    if hasattr(spec, "items"):
        return ", ".join(f"`{k}` {_shape(v)}" for k, v in spec.items())
    return _shape(spec)


def _shape(spec: Any) -> str:
    shape = "x".join(str(d) for d in spec.shape) or "()"
    return f"{shape} uint8" if spec.dtype == "uint8" else shape


def tasks_table(domain: str) -> str:
    """The Markdown table of one domain's tasks, from ``rlu.tasks``; a column equal for every
    task is said once above the table instead."""
    from rlu.tasks import DOMAINS, list_tasks

    if domain not in DOMAINS:
        raise ValueError(f"<!-- rlu:tasks {domain} -->: no such domain; domains: {DOMAINS}")
    tasks = list_tasks(domain)
    columns: dict[str, list[str]] = {
        "task": [f"`{t.id}`" for t in tasks],
        "observation": [_spec_text(t.observation_spec) for t in tasks],
        "action": [_spec_text(t.action_spec) for t in tasks],
        "episode steps": [f"{t.episode_length:,}" for t in tasks],
        "selection": [t.selection for t in tasks],
        "sequence length": [str(t.seq_length) for t in tasks],
        "paper episodes": [
            ", ".join(f"{k}: {v:,}" if k else f"{v:,}" for k, v in t.episodes.items()) or "-"
            for t in tasks
        ],
        "release files (shards)": [
            "; ".join(f"`{r.family}` ({_shards(r.shards)})" for r in t.release) for t in tasks
        ],
    }
    same = {k: v[0] for k, v in columns.items() if k != "task" and len(set(v)) == 1}
    table = {k: v for k, v in columns.items() if k not in same}
    out = []
    if same:
        shown = [f"{k} {v}" for k, v in same.items() if v != "-"]
        out += [f"Every task of the domain: {'; '.join(shown)}.", ""]
    out += ["| " + " | ".join(table) + " |", "|" + "---|" * len(table)]
    out += ["| " + " | ".join(row) + " |" for row in zip(*table.values(), strict=True)]
    return "\n".join(out) + f"\n\n{len(tasks)} tasks.\n"


def _shards(shards: Any) -> str:
    values = set(shards.values())
    if len(shards) == 1 and "" in shards:
        return str(shards[""])
    if len(values) == 1:
        return f"{values.pop()} per dataset"
    return ", ".join(f"{k}: {v}" for k, v in shards.items())


# ---- CLI ----------------------------------------------------------------------------------


def cli_reference() -> str:
    """Every ``rlu`` command's ``--help``, as argparse prints it at 80 columns."""
    from rlu.cli import build_parser

    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "80"
    try:
        parser = build_parser()
        out = ["## `rlu`", "", "```text", parser.format_help().rstrip(), "```", ""]
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                out += _subcommands("rlu", action)
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old
    return "\n".join(out)


def _subcommands(prefix: str, action: argparse._SubParsersAction) -> list[str]:
    out = []
    for name, sub in action.choices.items():
        out += [f"## `{prefix} {name}`", "", "```text", sub.format_help().rstrip(), "```", ""]
        for a in sub._actions:
            if isinstance(a, argparse._SubParsersAction):
                out += _subcommands(f"{prefix} {name}", a)
    return out


# ---- MkDocs events ------------------------------------------------------------------------

_MARKER = re.compile(r"<!-- rlu:(tasks|cli)\s*(\S*)\s*-->")


def on_config(config: Any) -> Any:
    """Put one nav entry per registered agent under the nav's "Agents" section."""
    for item in config["nav"] or []:
        if isinstance(item, dict) and AGENTS_NAV_TITLE in item:
            item[AGENTS_NAV_TITLE] = list(item[AGENTS_NAV_TITLE]) + [
                {e["title"]: e["page"]} for e in agent_entries()
            ]
            return config
    raise ValueError(f"mkdocs.yml: the nav has no {AGENTS_NAV_TITLE!r} section for the agents")


def on_files(files: Any, config: Any) -> Any:
    """Add the agents' generated pages."""
    from mkdocs.structure.files import File

    docs = Path(config["docs_dir"])
    settings = (docs / PAPER_SETTINGS).read_text()
    agents_md = (docs / "agents.md").read_text()
    for e in agent_entries():
        files.append(File.generated(config, e["page"], content=agent_page(e, settings, agents_md)))
    return files


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """Replace the ``<!-- rlu:... -->`` markers with the tables they name."""

    def replace(m: re.Match) -> str:
        return tasks_table(m.group(2)) if m.group(1) == "tasks" else cli_reference()

    return _MARKER.sub(replace, markdown)


# Docstrings are written for readers of the code as well, in reST's habits: ``:class:`X```
# roles and ``Text::`` before a literal block. Markdown shows the role's name and both colons;
# the page shows the code and one colon, as reST would.
_ROLE = re.compile(r":(?:func|class|meth|mod|attr|data|exc):(<code>)")
_LITERAL_INTRO = re.compile(r"::(</p>)")


def on_page_content(html: str, page: Any, config: Any, files: Any) -> str:
    """Drop reST's role names and literal-block colons from the rendered docstrings."""
    return _LITERAL_INTRO.sub(r":\1", _ROLE.sub(r"\1", html))
