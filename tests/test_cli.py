"""The README's main job runs end to end."""

from __future__ import annotations

import json

import pytest

from rlu.cli import main


def test_quickstart_end_to_end_at_tiny_cost(tmp_path, capsys):
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    out = tmp_path / "qs"
    argv = ["quickstart", "--out", str(out), "--steps", "5", "--eval-episodes", "1"]
    assert main([*argv, "--agents", "bc", "d4pg"]) == 0
    text = capsys.readouterr().out
    assert "validate: valid" in text and "| bc |" in text and "| random |" in text
    result = json.loads((out / "results.json").read_text())
    assert [r["policy"] for r in result["policies"]] == ["random", "bc", "d4pg"]
    bc, d4pg = (r["mean"] for r in result["policies"][1:])
    data = result["dataset_returns"]["mean"]
    row = next(line for line in text.splitlines() if line.startswith("| d4pg |"))
    assert row.endswith("| yes |" if d4pg > data else "| no |")
    assert f"Best offline RL agent here: d4pg, {d4pg / bc:.2f} times BC's return" in text
    assert "| bc | small, 5 |" in text and "is not comparable to these runs" in text
    # the paper's row for the task, from rlu's copy of its tables, in the table's order
    assert "The paper on this task (BC 386, D4PG 856, BCQ 445, BRAC 869, RABM 798;" in text
    assert result["dataset_returns"]["episodes"] == 40
    runs = out / "sweep" / "control_suite__cartpole_swingup"
    assert (runs / "bc" / "default" / "seed_0" / "result.json").exists()
    assert (out / "report.md").exists()
    if __import__("importlib").util.find_spec("matplotlib") is not None:
        png = (out / "quickstart.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
        assert "![policies beside the dataset's returns](quickstart.png)" in text


def test_quickstart_refuses_zero_workers_before_touching_out(tmp_path, capsys):
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    out = tmp_path / "qs"
    argv = ["--steps", "5", "--eval-episodes", "1", "--agents", "bc"]  # cheap if not refused
    with pytest.raises(SystemExit) as stop:
        main(["quickstart", "--out", str(out), "--workers", "0", *argv])
    assert stop.value.code == 2
    assert "--workers: 0 is out of range" in capsys.readouterr().err
    assert not out.exists()


def test_quickstart_never_deletes_what_it_did_not_write(tmp_path, capsys):
    """--out the dataset itself, a folder holding it, or a folder that is not a quick start's:
    refused before anything is touched; an unknown agent is refused before --out is replaced."""
    import shutil

    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    from rlu.data.bundled import bundled_dataset

    data = tmp_path / "data"
    shutil.copytree(bundled_dataset(), data)
    before = sorted(p.relative_to(data) for p in data.rglob("*"))
    cheap = ["--steps", "5", "--eval-episodes", "1", "--agents", "bc"]
    for out in (data, tmp_path, data / "inside"):
        assert main(["quickstart", "--dataset", str(data), "--out", str(out), *cheap]) == 2
        assert "could destroy it" in capsys.readouterr().err
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("years of work")
    assert main(["quickstart", "--out", str(mine), *cheap]) == 2
    assert "is not an rlu quick-start folder" in capsys.readouterr().err
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / "results.json").write_text("{}")
    assert main(["quickstart", "--out", str(earlier), "--agents", "nosuchagent"]) == 2
    assert "unknown continuous agent 'nosuchagent'" in capsys.readouterr().err
    assert (mine / "thesis.tex").read_text() == "years of work"
    assert (earlier / "results.json").exists()
    assert sorted(p.relative_to(data) for p in data.rglob("*")) == before


def test_quickstart_refuses_data_of_another_domain_before_touching_out(tmp_path, capsys):
    """The quick start runs on data of the bundled dataset's domain (the control suite): a
    dataset of another domain's task is refused, naming the task, before --out exists."""
    from rlu.data import Schema
    from rlu.data.synthetic import write_synthetic
    from rlu.tasks import get_task

    schema = Schema.for_task(get_task("locomotion/humanoid_corridor"))
    data = write_synthetic(tmp_path / "data", schema, 1, 3)
    out = tmp_path / "qs"
    cheap = ["--steps", "5", "--eval-episodes", "1", "--agents", "bc"]  # if it were not refused
    assert main(["quickstart", "--dataset", str(data), "--out", str(out), *cheap]) == 2
    err = capsys.readouterr().err
    assert "a dataset of task 'locomotion/humanoid_corridor'" in err
    assert "runs on data of the bundled dataset's domain (control_suite;" in err
    assert not out.exists()


def test_info_json_lists_every_episode_return(capsys):
    import numpy as np

    from rlu.data import open_dataset
    from rlu.data.bundled import bundled_dataset

    path = bundled_dataset()
    assert main(["info", str(path), "--json"]) == 0
    returns = json.loads(capsys.readouterr().out)["returns"]
    per_episode = returns["per_episode"]
    assert per_episode == open_dataset(path).episode_returns().tolist() and len(per_episode) == 40
    assert returns["mean"] == np.mean(per_episode) and returns["max"] == max(per_episode)
    assert main(["info", str(path)]) == 0
    assert "per_episode" not in capsys.readouterr().out  # the tree print stays short


def test_train_and_evaluate_defaults_are_quick():
    """A short train evaluates once, at the end; long ones at most 10 times; one torch thread."""
    from rlu.cli import build_parser
    from rlu.commands._options import from_args
    from rlu.training.config import RunSettings

    parser = build_parser()
    base = ["train", "--task", "t", "--agent", "bc", "--dataset", "d", "--out", "o"]
    short = from_args(RunSettings, parser.parse_args([*base, "--steps", "20"]))
    assert short.eval_period(20) == 20 and short.torch_threads == 1  # once, at the end
    assert short.eval_period(1_000_000) == 100_000  # ten times
    assert short.eval_period(50_000) == 10_000  # never more often than every 10,000 steps
    five = from_args(RunSettings, parser.parse_args([*base, "--eval-every", "5"]))
    assert five.eval_period(20) == 5 and RunSettings().eval_period(20) == 20  # library = CLI
    never = from_args(RunSettings, parser.parse_args([*base, "--eval-every", "-1"]))
    assert never.eval_period(9) == 0
    evaluate = from_args(RunSettings, parser.parse_args(["evaluate", "run"]))
    assert evaluate.torch_threads == 1 and evaluate.eval_episodes == RunSettings().eval_episodes


def test_evaluate_sets_its_threads(tmp_path, capsys):
    torch = pytest.importorskip("torch")
    pytest.importorskip("gymnasium")
    from rlu.training.train import train
    from tests.fakes import train_config
    from tests.train.pendulum import write_dataset

    data = write_dataset(tmp_path / "data", "test/pendulum", episodes=4)
    env = "tests.train.pendulum:make_env"
    cfg = train_config(task="test/pendulum", agent="tests.train.fake_agent", dataset=str(data),
                      steps=3, eval_every=-1, checkpoint_every=3, env=env)  # fmt: skip
    train(cfg, tmp_path / "run", progress=False)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        argv = ["evaluate", str(tmp_path / "run"), "--eval-episodes", "2", "--eval-envs", "2",
                "--json"]  # fmt: skip
        assert main(argv) == 2  # the run's env factory is named in its config.json only
        assert f"if you trust it, name it yourself: --env {env}" in capsys.readouterr().err
        argv += ["--env", env]
        assert main(argv) == 0
        assert torch.get_num_threads() == 1  # the default
        assert len(json.loads(capsys.readouterr().out)["returns"]) == 2
        with pytest.raises(SystemExit) as stop:  # refused by the parser
            main([*argv, "--threads", "0"])
        assert stop.value.code == 2
        assert "--threads: 0 is out of range; give a value >= 1" in capsys.readouterr().err
    finally:
        torch.set_num_threads(before)


def test_info_of_a_missing_path_or_a_file_says_so_not_unknown_task(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("x")
    for target, says in [
        (str(tmp_path / "nope"), "is neither a task id nor a dataset directory"),
        ("./runs/nope", "is neither a task id nor a dataset directory"),
        (str(tmp_path / "notes.txt"), "is a file, not a dataset directory"),
    ]:
        assert main(["info", target]) == 2
        err = capsys.readouterr().err
        assert f"{target} {says}" in err and "unknown task id" not in err, err
    assert main(["info", "control_suite/walker_wlak"]) == 2  # an id's typo: the closest ids
    assert "Closest: control_suite/walker_walk" in capsys.readouterr().err
    assert main(["info", "runs/nope"]) == 2  # an id or a relative path: both are said
    err = capsys.readouterr().err
    assert "unknown task id 'runs/nope'" in err and "Nor is runs/nope a dataset directory" in err


def test_version_and_did_you_mean(capsys):
    from rlu import __version__

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"rlu {__version__}"
    for argv, says in [
        (["trian"], "invalid choice: 'trian'"),
        (["list", "--jsn"], "unrecognized arguments: --jsn (did you mean --json?)"),
        (["train", "--out", "o", "--stpes", "3"], "--stpes (did you mean --steps?)"),
        (["evaluate", "run", "--eval-episods", "2"], "(did you mean --eval-episodes?)"),
    ]:
        with pytest.raises(SystemExit) as e:
            main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and says in err, err
    with pytest.raises(SystemExit):
        main(["trian"])
    assert "did you mean 'train'?" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["list", "--zzzzzz"])
    assert "`rlu list --help` lists the options" in capsys.readouterr().err


def test_help_names_real_commands():
    """Every `rlu WORD` in any help text is a command (--agent's help named `rlu list-agents`,
    which did not exist), and `rlu agents` lists every agent --agent takes."""
    import argparse
    import re

    from rlu.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    commands = set(sub.choices)
    prose = {"ships", "was", "writes", "reads", "wrote", "made", "makes", "does", "is", "has"}

    def texts(p):
        yield p.description or ""
        yield p.epilog or ""
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for child in a.choices.values():
                    yield from texts(child)
            yield a.help or ""

    named = [w for text in texts(parser) for w in re.findall(r"\brlu ([a-z][a-z-]*)", text)]
    assert "agents" in named  # --agent's help
    assert [w for w in named if w not in commands and w not in prose] == []
    assert "agents" in commands


def test_rlu_agents_lists_the_registry(capsys):
    from rlu.agents import AGENTS

    assert main(["agents", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["name"], r["actions"] == "discrete") for r in rows] == list(AGENTS)
    assert all(r["summary"] for r in rows)
    assert main(["agents"]) == 0
    text = capsys.readouterr().out
    assert text.splitlines()[1].split()[:2] == ["bc", "continuous"]
    assert "et al" in text and f"{len(AGENTS)} agents" in text


def test_a_run_that_never_evaluates_says_so(tmp_path, capsys):
    pytest.importorskip("torch")
    pytest.importorskip("gymnasium")
    from tests.train.pendulum import write_dataset

    data = write_dataset(tmp_path / "data", "test/pendulum", episodes=2)
    argv = ["train", "--task", "test/pendulum", "--agent", "tests.train.fake_agent", "--dataset",
            str(data), "--out", str(tmp_path / "run"), "--steps", "3", "--eval-every", "-1",
            "--env", "tests.train.pendulum:make_env", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    out = capsys.readouterr().out.strip()
    assert out == (
        f"{tmp_path / 'run'}: 3 steps (small preset), not evaluated (--eval-every -1); score it "
        f"with `rlu evaluate {tmp_path / 'run'}`"
    )
    assert "final evaluation return not evaluated" not in out


def test_an_option_of_a_field_with_a_strict_upper_bound_refuses_the_bound(capsys):
    """``lt`` (strictly below, as rlu.files.bounds writes it) is the parser's too: a field
    bounded by it gets an option that refuses the bound itself and what lies above."""
    import argparse
    import dataclasses

    from rlu.commands._options import add_options, checked
    from rlu.files import bounds

    parse = checked(float, bounds(gt=0.0, lt=1.0), "--rate")
    assert parse("0.5") == 0.5 and parse("0.999") == 0.999
    for bad in ("1.0", "1.5", "0.0", "nan"):
        with pytest.raises(argparse.ArgumentTypeError, match="out of range; give a finite "
                           "value > 0.0 and < 1.0"):  # fmt: skip
            parse(bad)
    with pytest.raises(argparse.ArgumentTypeError, match="give a value >= 0 and < 10"):
        checked(int, bounds(min=0, lt=10), "--n")("10")
    assert checked(int, bounds(min=0, lt=10), "--n")("9") == 9

    @dataclasses.dataclass(frozen=True)
    class Settings:
        rate: float = dataclasses.field(default=0.5, metadata=bounds(min=0.0, lt=1.0))
        """A rate."""

    parser = argparse.ArgumentParser(prog="x")
    add_options(parser, Settings)
    assert parser.parse_args(["--rate", "0.0"]).rate == 0.0
    with pytest.raises(SystemExit):
        parser.parse_args(["--rate", "1.0"])
    assert "--rate: 1.0 is out of range; give a finite value >= 0.0 and < 1.0" in (
        capsys.readouterr().err
    )
