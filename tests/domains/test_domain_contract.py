"""The contract every registered domain meets, run over ``rlu.domains.DOMAINS``: a new domain is
tested by being registered (as the agents' contract test does for agents).

Every domain's tasks resolve by id, by their Gymnasium id's parts and by each TFDS builder's
example name; every release family its tasks name is a family the reader decodes, and each
dataset's object names build; its env is made and stepped where its extra is installed (else the
test skips naming the extra), or, for a data-only domain (DeepMind Lab), refused saying why;
where a release shard of the domain is among the fixtures (files TensorFlow wrote), it converts
from the command line, an agent trains on it for a few steps and is evaluated in the env, and
``rlu report`` reads the run (a data-only domain's run trains without evaluating, and
``rlu evaluate`` and ``rlu report`` refuse it with the reason).
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

from rlu.domains import DOMAINS, Domain, get_domain
from rlu.tasks import TASKS, list_tasks, resolve_task
from rlu.types import DiscreteSpec, RluError

ROOT = Path(__file__).resolve().parents[2]
SHARED = Path(os.environ.get("RLU_SHARED", ROOT.parent / "shared"))
# Release shards TensorFlow wrote: the shared fixtures and the repo's own (tests/fixtures).
FIXTURE_ROOTS = (
    SHARED / "fixtures" / "rlu_release" / "data",
    ROOT / "tests" / "fixtures" / "release",
)
NAMES = list(DOMAINS)


def test_the_registry_is_the_task_registrys_domains():
    from rlu import tasks

    assert tasks.DOMAINS == tuple(DOMAINS)
    assert {t.domain for t in TASKS.values()} == set(DOMAINS)
    for name, domain in DOMAINS.items():
        assert isinstance(domain, Domain) and domain.name == name
        # a domain is in one place: its folder (or module), which holds every module it names
        home = f"rlu.domains.{name}"
        assert (ROOT / "rlu" / "domains" / name / "__init__.py").is_file() or (
            ROOT / "rlu" / "domains" / f"{name}.py"
        ).is_file()
        for module in (domain.env_module, domain.release_module):
            assert module is None or module == home or module.startswith(home + "."), module
    with pytest.raises(RluError, match="unknown domain 'nope'; use one of"):
        get_domain("nope")


@pytest.mark.parametrize("name", NAMES)
def test_tasks_resolve(name):
    domain = DOMAINS[name]
    tasks = list_tasks(name)
    assert tasks, f"domain {name} has no tasks"
    for t in tasks:
        assert t.id == f"{name}/{t.name}" and t.domain == name
        assert resolve_task(t.id).task is t
        assert t.gym_id == f"rlu/{name}-{t.name}-v0"
        assert t.selection in ("online", "offline") and t.episode_length > 0
    for builder, example in domain.tfds_examples.items():
        assert builder in domain.tfds_builders
        ref = resolve_task(example)
        assert ref.task.domain == name and ref.family == domain.tfds_builders[builder]
    assert set(domain.tfds_examples) == set(domain.tfds_builders)


@pytest.mark.parametrize("name", NAMES)
def test_release_families_decode_and_name_their_objects(name):
    from rlu.data.release import catalog
    from rlu.data.release.families import FAMILIES

    for t in list_tasks(name):
        assert t.release, f"{t.id} names no release files"
        for rel in t.release:
            assert rel.family in FAMILIES, f"{t.id}: family {rel.family!r} has no reader"
            assert set(rel.shards) == set(t.datasets) or set(rel.shards) == {""}
            for binding, n in rel.shards.items():
                names = rel.shard_names(binding)
                assert len(names) == n and names[0].startswith(rel.family + "/")
        sel = catalog.select(t.id)
        assert sel.objects and sel.release is t.release[0]


@pytest.mark.parametrize("name", NAMES)
def test_report_fields_name_what_the_report_has(name):
    """The entry's paper conditions state every condition, its recurrent tasks are its own, its
    figures are panels the report computes and renders, a normalised domain ships both
    reference scores of every task, and a domain with a paper table has the paper's numbers."""
    from rlu.report.conditions import CONDITIONS
    from rlu.report.numbers import PANELS, load_paper_results
    from rlu.report.render import RENDERERS

    domain = DOMAINS[name]
    paper = domain.paper_conditions
    assert tuple(paper.statements) == CONDITIONS
    assert set(paper.recurrent_tasks) <= {t.id for t in list_tasks(name)}
    assert domain.report_figures and set(domain.report_figures) <= set(PANELS) & set(RENDERERS)
    if domain.normalised:
        from rlu.evaluation.scores import load_reference_scores

        for ref in ("random_scores", "atari_best_behaviour"):
            missing = {t.id for t in list_tasks(name)} - set(load_reference_scores(ref))
            assert not missing, f"rlu/resources/{ref}.json has no score for {sorted(missing)}"
    assert (domain.paper_table is not None) == (name in load_paper_results())


@pytest.mark.parametrize("name", NAMES)
def test_generation_fields_resolve(name):
    """A domain whose data online agents generate names an agent per scale, each with settings
    in ``rlu.generate.scales``; any other names none and ``get_scale`` says who trains what."""
    from rlu.generate.config import SCALES
    from rlu.generate.scales import BEHAVIOUR, get_scale

    domain = DOMAINS[name]
    task = list_tasks(name)[0]
    if domain.generation not in ("runs", "snapshots"):
        assert not domain.behaviour_agents
        with pytest.raises(RluError, match="rlu generate trains behaviour agents for the "):
            get_scale(task, SCALES[0])
        return
    assert tuple(domain.behaviour_agents) == SCALES
    for scale, agent in domain.behaviour_agents.items():
        assert (agent, scale) in BEHAVIOUR
        sc = get_scale(task, scale)
        assert sc.online.agent == agent and sc.runs >= 1


# Domains without a release shard among the fixtures, which the convert-train-evaluate-report
# test below therefore never runs, each with why; a new domain adds a shard (tests/fixtures/
# release, written by TensorFlow: scripts/fixtures) or a line here.
NO_FIXTURE: dict[str, str] = {}


def _installed(domain: Domain) -> str | None:
    missing = [p for p in domain.packages if importlib.util.find_spec(p) is None]
    if missing and domain.env_install:  # no extra installs it (DeepMind Lab)
        return f"{', '.join(missing)} is not installed: {domain.env_install}"
    return (
        f"the {domain.extra!r} extra is not installed ({', '.join(missing)})" if missing else None
    )


@pytest.mark.parametrize("name", NAMES)
def test_env_matches_the_task(name):
    domain = DOMAINS[name]
    if domain.data_only:  # no env: making one says so, with or without its packages
        from rlu.envs import make_env

        task = list_tasks(name)[0]
        with pytest.raises(RluError, match="^" + re.escape(f"{task.id}: {domain.data_only}")):
            make_env(task.id, seed=0)
        return
    why = _installed(domain)
    if why:
        pytest.skip(why)
    from rlu.envs import make_env

    task = list_tasks(name)[0]
    settings = {domain.camera_setting: False} if domain.camera_setting else {}
    env = make_env(task.id, seed=0, **settings)
    try:
        obs, _ = env.reset(seed=0)
        action = env.action_space.sample()
        obs2, reward, terminated, truncated, _ = env.step(action)
        assert np.isfinite(reward) and isinstance(terminated, bool)
        if isinstance(task.action_spec, DiscreteSpec):
            assert env.action_space.n == task.action_spec.num_values
        assert env.spec.id == task.gym_id
    finally:
        env.close()


def _fixture_shards() -> list[tuple[str, str, str]]:
    """(shard path, family, task id) for every fixture shard of a registered task's files."""
    found = []
    for t in TASKS.values():
        for rel in t.release:
            for binding in rel.shards:
                prefix = rel.prefix(binding)
                for root in FIXTURE_ROOTS:
                    hits = sorted(root.glob(prefix + "-*-of-*"))
                    found += [(str(h), rel.family, t.id) for h in hits[:1]]
    return found


SHARDS = [
    # the shared Pong shard's actions are random in [0, 18) (its README: random contents), which
    # Pong's 6 actions refuse at conversion: it is converted and played as a game of 18 actions
    (shard, family, "atari/Zaxxon" if task == "atari/Pong" else task)
    for shard, family, task in _fixture_shards()
]


def test_every_fixture_shard_belongs_to_a_domain():
    # the fixtures hold control-suite windows and Atari transitions at least
    assert {TASKS[t].domain for _, _, t in SHARDS} >= {"control_suite", "atari"}  # rlu-domains: ok


def test_every_domain_has_a_fixture_shard_or_says_why():
    have = {TASKS[t].domain for _, _, t in SHARDS}
    assert not have & set(NO_FIXTURE), "a domain of NO_FIXTURE has a shard now: drop its line"
    assert have | set(NO_FIXTURE) == set(DOMAINS), (
        f"no fixture shard of {sorted(set(DOMAINS) - have - set(NO_FIXTURE))}: add one or say why "
        "in NO_FIXTURE"
    )


# slow: 3-9 s a case on a 2-core machine (torch's import, a report)
@pytest.mark.slow
@pytest.mark.parametrize("shard,family,task", SHARDS, ids=[s[2] for s in SHARDS])
def test_a_fixture_shard_converts_trains_evaluates_and_reports(
    tmp_path, capsys, shard, family, task
):
    pytest.importorskip("torch")
    pytest.importorskip("google_crc32c")
    domain = DOMAINS[TASKS[task].domain]
    why = _installed(domain)
    if why and not domain.data_only:
        pytest.skip(why)
    from rlu.cli import main

    data, run = tmp_path / "data", tmp_path / "run"
    args = ["convert", shard, "--family", family, "--task", task, "--out", str(data)]
    if domain.challenges:
        args += ["--challenge", domain.challenges[0]]
    assert main(args) == 0
    agent, batch = ("dqn", "atari.batch_size=4") if TASKS[task].discrete else ("bc", "batch_size=4")
    if domain.data_only:  # trains offline; evaluating and reporting say there is no env
        argv = ["train", "--task", task, "--agent", agent, "--dataset", str(data), "--out",
                str(run), "--steps", "3", "--eval-every", "-1", "--device", "cpu", "--quiet",
                batch]  # fmt: skip
        assert main(argv) == 0
        result = json.loads((run / "result.json").read_text())
        assert result["steps"] == 3 and result["score"] is None
        capsys.readouterr()
        assert main(["evaluate", str(run), "--eval-episodes", "1"]) == 2
        assert domain.data_only in capsys.readouterr().err
        assert main(["report", str(run), "--out", str(tmp_path / "report")]) == 2
        assert "has no evaluation score" in capsys.readouterr().err
        return
    argv = ["train", "--task", task, "--agent", agent, "--dataset", str(data), "--out", str(run),
            "--steps", "3", "--eval-every", "0", "--eval-episodes", "1", "--eval-envs", "1",
            "--eval-max-steps", "5", "--device", "cpu", "--quiet", batch]  # fmt: skip
    assert main(argv) == 0
    result = json.loads((run / "result.json").read_text())
    assert result["steps"] == 3 and np.isfinite(result["final_eval"]["mean"])
    assert 1 <= result["final_eval"]["lengths"][0] <= 5
    assert main(["report", str(run), "--out", str(tmp_path / "report")]) == 0
    assert any((tmp_path / "report").iterdir())
