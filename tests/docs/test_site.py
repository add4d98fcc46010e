"""The site's generated pages (scripts/docs_hooks.py): one per registered agent with the rows of
docs/paper_settings.md that name it, the task tables, the CLI reference, and a nav that holds
every page. The build itself (``mkdocs build --strict``) runs in scripts/test.sh."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.scripts import load_script

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
PAPER_BASELINES = {("bc", False), ("d4pg", False), ("bcq", False), ("brac", False),
                   ("rabm", False), ("bc", True), ("dqn", True), ("iqn", True), ("bcq", True),
                   ("rem", True)}  # fmt: skip

hooks = load_script("docs_hooks")


def _page(name: str, discrete: bool) -> str:
    pytest.importorskip("markdown")  # the anchors are Python-Markdown's (the docs extra)
    entry = next(e for e in hooks.agent_entries() if (e["name"], e["discrete"]) == (name, discrete))
    return hooks.agent_page(
        entry, (DOCS / "paper_settings.md").read_text(), (DOCS / "agents.md").read_text()
    )


def test_one_page_per_registered_agent():
    from rlu.agents import AGENTS

    entries = hooks.agent_entries()
    both = {n for n, d in AGENTS if AGENTS.get((n, not d)) == AGENTS[(n, d)]}  # dt
    assert both == {"dt"}
    one_each = [(n, d) for n, d in AGENTS if n not in both or d]
    assert [(e["name"], e["discrete"] if e["name"] not in both else True) for e in entries] == (
        one_each
    )
    assert {e["page"] for e in entries} == {
        f"agents/{m.rsplit('.', 1)[-1]}.md" for m in AGENTS.values()
    }
    assert len({e["page"] for e in entries}) == len(entries) == len(set(AGENTS.values()))
    for e in entries:
        names = hooks.module_names(e["file"].read_text())
        assert {"Config", "Agent", "PRESETS", "GRID"} <= set(names), e["module"]
        assert names["PRESETS"].startswith("PRESETS") and '"paper"' in names["PRESETS"]


@pytest.mark.parametrize("name, discrete", sorted(PAPER_BASELINES))
def test_paper_baselines_carry_their_paper_rows(name, discrete):
    from rlu.agents import AGENTS

    text = _page(name, discrete)
    assert f"::: {AGENTS[(name, discrete)]}\n" in text
    assert "From [" in text, f"{name}: no row of paper_settings.md"


def test_rows_are_the_agents_own():
    d4pg = _page("d4pg", False)
    assert "| D4PG | networks |" in d4pg and "| D4PG | n-step |" in d4pg
    assert "| BCQ | networks, algorithm |" not in d4pg
    # the discrete BCQ gets the Atari rows, not the continuous BCQ's VAE
    bcq_atari = _page("bcq", True)
    assert "| BCQ | threshold 0.5" in bcq_atari and "VAE 750-750" not in bcq_atari
    bc_atari = _page("bc", True)
    assert "| chosen learning rates |" in bc_atari and "mixture of 5 Gaussians" not in bc_atari
    # dopamine_dqn: its whole section, named in that section's prose
    dopamine = _page("dopamine_dqn", True)
    assert "| optimiser | `tf.train.RMSPropOptimizer" in dopamine
    assert "atari-data-generation-dopamines-online-dqn-rlu-generate-atari" in dopamine


def test_a_module_for_both_action_types_gets_one_page_with_its_own_rows():
    text = _page("dt", None)
    assert text.startswith("# `dt` (continuous and discrete actions)")
    assert "From [Decision Transformer" in text and "| context length K |" in text
    assert "AtariSettings" not in text  # its `atari` field is its own settings, not the table's
    assert "::: rlu.agents.dt.AtariDT\n" in text  # and they are on the page


@pytest.mark.parametrize("name, discrete", [("iql", False), ("crr", False), ("cql", True)])
def test_agents_beyond_the_paper_say_so(name, discrete):
    text = _page(name, discrete)
    assert "is not one of the paper's baselines" in text and "From [" not in text


def test_task_tables_list_every_task():
    from rlu.tasks import DOMAINS, list_tasks

    for domain in DOMAINS:
        table = hooks.tasks_table(domain)
        for task in list_tasks(domain):
            assert f"| `{task.id}` |" in table
        assert f"{len(list_tasks(domain))} tasks." in table
    assert "| 56 in [-1, 1] |" in hooks.tasks_table("locomotion")  # humanoid actions
    assert "observation 84x84x4 uint8" in hooks.tasks_table("atari")  # said once, above
    with pytest.raises(ValueError, match="no such domain"):
        hooks.tasks_table("mujoco")


def test_every_domain_page_has_its_table():
    from rlu.tasks import DOMAINS

    for domain in DOMAINS:
        assert f"<!-- rlu:tasks {domain} -->" in (DOCS / "domains" / f"{domain}.md").read_text()


def test_cli_reference_has_every_command():
    from rlu.cli import build_parser

    text = hooks.cli_reference()
    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    for name in sub.choices:
        assert f"## `rlu {name}`" in text


def test_reST_roles_and_literal_colons_are_dropped():
    html = "<p>see :class:<code>X</code> and :func:<code>f</code>; layout::</p>"
    assert hooks.on_page_content(html, None, None, None) == (
        "<p>see <code>X</code> and <code>f</code>; layout:</p>"
    )


def test_nav_holds_every_page():
    yaml = pytest.importorskip("yaml")
    # mkdocs.yml has no !tags, so plain YAML reads it
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    listed: set[str] = set()

    def walk(items):
        for item in items:
            if isinstance(item, str):
                listed.add(item)
            else:
                for value in item.values():
                    walk(value) if isinstance(value, list) else listed.add(value)

    walk(config["nav"])
    pages = {str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md")}
    assert pages == listed, f"not in the nav: {pages - listed}; missing: {listed - pages}"
    assert "Agents" in [next(iter(i)) for i in config["nav"] if isinstance(i, dict)]


def test_lists_get_the_blank_line_markdown_needs():
    pytest.importorskip("griffe")
    lists = load_script("docs_griffe").blank_line_before_lists
    assert lists("Deviations:\n- one\n- two\nafter") == "Deviations:\n\n- one\n- two\nafter"
    assert lists("  lead:\n  - item") == "  lead:\n\n  - item"
    # already apart, a continuation line, a code block: unchanged
    for text in ("a:\n\n- b", "- item\n  wraps\n- next", "code::\n\n    x = 1\n    - y"):
        assert lists(text) == text


def test_the_api_reference_has_every_module():
    import re

    from rlu.agents import AGENTS

    modules = set()
    for path in (ROOT / "rlu").rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        modules.add(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    # the CLI's own modules are on the command-line page, the agents on their own pages
    left_out = {"rlu.__main__", "rlu.cli", "rlu.resources", *AGENTS.values()}
    wanted = {m for m in modules if m not in left_out and not m.startswith("rlu.commands")}
    text = "\n".join(p.read_text() for p in DOCS.rglob("*.md"))
    documented = set(re.findall(r"^::: (\S+)$", text, flags=re.M))
    assert wanted <= documented, f"not in docs/reference/: {sorted(wanted - documented)}"
