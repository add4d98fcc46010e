"""Every configured value checked when its config is made (issue 39, third round, item 3): the
bounds of every number of every agent config, of the Atari agents' shared settings, of the run
settings; refused from Python, from an override and from a file alike with a ConfigError naming
the config, the field, the value and the bound (and the file and key, or the command line, that
gave it), before any folder of the run exists; a YAML config nested too deep refused."""

from __future__ import annotations

import dataclasses
import importlib
import math
import typing

import pytest

from rlu.files import Float, Int, ListOf, Optional, Shape, check_fields, field_shape
from rlu.types import ConfigError, FormatError, RluError

pytest.importorskip("torch")


def _agent_modules() -> list[tuple[str, bool, typing.Any]]:
    from rlu.agents import AGENTS

    return [(n, d, importlib.import_module(p)) for (n, d), p in AGENTS.items()]


def _config_classes() -> list[type]:
    """Every agent config class, the dataclasses composed in them, TrainConfig, SweepConfig,
    FQEConfig, RunSettings and its Runtime, GenerateConfig and its Backend, OnlineConfig,
    RwrlSettings and its Challenge."""
    from rlu.domains.rwrl.env import RwrlSettings
    from rlu.evaluation.fqe import FQEConfig
    from rlu.generate.config import GenerateConfig
    from rlu.generate.online import OnlineConfig
    from rlu.training.config import RunSettings
    from rlu.training.sweep import SweepConfig
    from rlu.training.train import TrainConfig

    todo = [m.Config for _, _, m in _agent_modules()]
    todo += [RunSettings, TrainConfig, SweepConfig, FQEConfig]
    todo += [GenerateConfig, OnlineConfig, RwrlSettings]
    out: list[type] = []
    while todo:
        cls = todo.pop()
        if cls in out:
            continue
        out.append(cls)
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if dataclasses.is_dataclass(hints[f.name]):
                todo.append(hints[f.name])
    return sorted(out, key=lambda c: (c.__module__, c.__name__))


def _numbers(shape: Shape) -> tuple[Shape, ListOf | None]:
    """(the number shape inside an Optional / a tuple, the tuple's shape or None)."""
    if isinstance(shape, Optional):
        shape = shape.inner
    if isinstance(shape, ListOf):
        return shape.item, shape
    return shape, None


def _numeric_fields() -> list[tuple[type, str, Shape, ListOf | None]]:
    out = []
    for cls in _config_classes():
        for f in dataclasses.fields(cls):
            number, tup = _numbers(field_shape(cls, f.name))
            if isinstance(number, Int | Float):
                out.append((cls, f.name, number, tup))
    return out


NUMERIC = _numeric_fields()
IDS = [f"{c.__name__}.{n}" for c, n, _, _ in NUMERIC]


def test_every_number_of_every_config_has_a_lower_and_an_upper_bound():
    assert len(NUMERIC) > 200  # every agent's, AtariSettings', RunSettings', TrainConfig's
    classes = {c.__name__ for c, _, _, _ in NUMERIC}
    assert {"GenerateConfig", "Backend", "OnlineConfig", "RwrlSettings", "Challenge"} <= classes
    unbounded = [
        f"{cls.__module__}.{cls.__name__}.{name}"
        for cls, name, s, _ in NUMERIC
        if (s.min is None and getattr(s, "gt", None) is None)
        or (s.max is None and getattr(s, "lt", None) is None)
    ]
    assert not unbounded, unbounded
    long = [f"{c.__name__}.{n}" for c, n, _, t in NUMERIC if t is not None and t.max_len > 10**6]
    assert not long, long


def test_every_preset_and_every_grid_value_lies_inside_its_bounds():
    from rlu.agents import make_config

    for name, discrete, module in _agent_modules():
        for preset, config in module.PRESETS.items():
            check_fields(config)  # would raise: a preset out of its own bounds
            for f in dataclasses.fields(config):
                inner = getattr(config, f.name)
                if dataclasses.is_dataclass(inner):
                    check_fields(inner)
            for key, values in module.GRID.items():
                for value in values:
                    make_config(name, discrete, preset, **{key: value})


def _outside(s: Int | Float) -> list[typing.Any]:
    """Values just outside each bound of number shape ``s``."""
    if isinstance(s, Int):
        return [s.min - 1, s.max + 1]
    out = []
    for bound, sign in ((s.min, -1), (s.max, 1)):
        if bound is not None:
            out.append(bound + sign * max(abs(bound) * 1e-6, 1e-9))
    out += [b for b in (s.gt, s.lt) if b is not None]  # the strict bound itself
    return out


def _instances(cls: type) -> list[typing.Any]:
    """Valid instances of ``cls`` to replace one field of: an agent's presets (or its
    composed settings'), a default RunSettings, a small TrainConfig or SweepConfig."""
    from rlu.devices import Runtime
    from rlu.domains.rwrl.env import Challenge, RwrlSettings
    from rlu.evaluation.fqe import FQEConfig
    from rlu.generate.config import GenerateConfig
    from rlu.generate.online import OnlineConfig
    from rlu.training.config import RunSettings
    from rlu.training.sweep import SweepConfig
    from rlu.training.train import TrainConfig
    from rlu.workers import Backend

    if cls in (RunSettings, Runtime, FQEConfig, Backend, Challenge):
        return [cls()]
    if cls is GenerateConfig:
        return [GenerateConfig("control_suite/cartpole_swingup", runs=2)]
    if cls is OnlineConfig:
        return [OnlineConfig("d4pg", episodes=2, env_steps=100)]
    if cls is RwrlSettings:
        return [RwrlSettings(Challenge())]
    if cls is SweepConfig:
        return [SweepConfig(tasks=("t",), agents=("bc",), seeds=(0, 1), max_configs=2)]
    if cls is TrainConfig:
        return [TrainConfig(task="t", agent="bc", dataset=("a", "b"), weights=(1.0, 2.0))]
    found = []
    for _, _, module in _agent_modules():
        for config in module.PRESETS.values():
            if type(config) is cls:
                found.append(config)
            for f in dataclasses.fields(config):
                if type(getattr(config, f.name)) is cls:
                    found.append(getattr(config, f.name))
    return found[:1]


def _valid(config: typing.Any, name: str) -> typing.Any:
    value = getattr(config, name)
    return value if value is not None else 1.0


@pytest.mark.parametrize(("cls", "name", "shape", "tup"), NUMERIC, ids=IDS)
def test_a_value_just_outside_a_bound_is_refused_from_python(cls, name, shape, tup):
    (config,) = _instances(cls)
    for bad in [*_outside(shape), *([math.nan, math.inf] if isinstance(shape, Float) else [True])]:
        if tup is None:
            value = bad
        else:  # one item of the tuple out of range; the others as they are
            items = tuple(_valid(config, name))
            value = (bad, *items[1:])
        with pytest.raises(ConfigError) as e:
            dataclasses.replace(config, **{name: value})
        message = str(e.value)
        assert f"{cls.__name__} field '{name}" in message, message
        if not isinstance(bad, bool) and math.isfinite(bad):
            assert str(bad) in message, message  # the value
        bounds = [b for b in (shape.min, shape.max, getattr(shape, "gt", None),
                              getattr(shape, "lt", None)) if b is not None]  # fmt: skip
        assert any(str(b) in message for b in bounds), message  # the bound


@pytest.mark.parametrize(("cls", "name", "shape", "tup"), NUMERIC, ids=IDS)
def test_a_value_just_outside_a_bound_is_refused_as_an_override_or_in_a_file(
    cls, name, shape, tup, tmp_path, monkeypatch
):
    import json

    from rlu.agents import make_config
    from rlu.devices import Runtime
    from rlu.domains.rwrl.env import Challenge, RwrlSettings
    from rlu.evaluation.fqe import FQEConfig
    from rlu.generate.config import GenerateConfig
    from rlu.generate.online import OnlineConfig
    from rlu.training.config import RunSettings, read_config_file
    from rlu.training.sweep import SweepConfig
    from rlu.training.train import TrainConfig
    from rlu.workers import Backend

    if cls is FQEConfig:
        pytest.skip("no file holds FQE's settings (rlu report --fqe-steps: the parser's range)")
    if cls is OnlineConfig:
        pytest.skip("no file or flag sets a behaviour run's settings (rlu.generate.scales)")
    if cls in (RwrlSettings, Challenge):  # rlu.make_env's settings: the task named too
        import rlu

        for bad in _outside(shape):
            with pytest.raises(ConfigError) as e:
                rlu.make_env("rwrl/cartpole_swingup", challenge="easy", **{name: bad})
            message = str(e.value)
            assert message.startswith("rwrl/cartpole_swingup: ") and f"field '{name}'" in message
            assert str(bad) in message, message
        return
    if cls in (GenerateConfig, Backend):  # rlu generate's options: the flag, value and bound
        _refused_by_rlu_generate(cls, name, shape, tmp_path, monkeypatch)
        return
    keys = {TrainConfig: name, RunSettings: f"run.{name}", Runtime: f"run.runtime.{name}",
            SweepConfig: name}  # fmt: skip
    if cls in keys:  # in a run or sweep config file: the file and the key named
        path = tmp_path / "c.json"
        for bad in _outside(shape):
            value = bad if tup is None else [bad, 1.0]
            data = value
            for part in reversed(keys[cls].split(".")):
                data = {part: data}
            path.write_text(json.dumps(data))
            with pytest.raises(FormatError, match=f"{path}: field '{keys[cls]}"):
                read_config_file(str(path), SweepConfig if cls is SweepConfig else TrainConfig)
        return

    agents = [
        (n, d, path)
        for n, d, m in _agent_modules()
        for path in (
            [name]
            if cls is m.Config
            else [
                f"{f.name}.{name}"
                for f in dataclasses.fields(m.Config)
                if typing.get_type_hints(m.Config)[f.name] is cls
            ]
        )  # fmt: skip
    ]
    agent, discrete, path = agents[0]
    current = make_config(agent, discrete, "small")
    for part in path.split("."):
        current = getattr(current, part)
    for bad in _outside(shape):
        value = bad if tup is None else [bad, *current[1:]]
        with pytest.raises(ConfigError, match=f"field '{name}") as e:
            make_config(agent, discrete, "small", **{path: value})
        assert f"(override {path}=" in str(e.value)


def _refused_by_rlu_generate(cls: type, name: str, shape: Int | Float, tmp_path, monkeypatch):
    import contextlib
    import io

    import rlu.generate
    from rlu.cli import main

    def generated(*args, **kw):  # a value not refused would start the generation
        raise AssertionError(f"rlu generate took {name} out of its bounds")

    monkeypatch.setattr(rlu.generate, "generate", generated)

    flag = dict(next(f for f in dataclasses.fields(cls) if f.name == name).metadata).get(
        "flag", "--" + name.replace("_", "-")
    )
    extra = ["--backend", "ray"] if name == "gpus_per_job" else []  # local runs ask for none
    for bad in _outside(shape):
        err = io.StringIO()
        argv = ["generate", "control_suite/cartpole_swingup", "--out", str(tmp_path / "out"),
                *extra, f"{flag}={bad}"]  # fmt: skip
        with contextlib.redirect_stderr(err):
            try:
                code = main(argv)  # the library's ConfigError
            except SystemExit as stop:  # the parser's range
                code = int(stop.code)
        message = err.getvalue()
        assert code == 2, message
        assert str(bad) in message and (flag in message or f"field '{name}'" in message), message
        bounds = [b for b in (shape.min, shape.max, getattr(shape, "gt", None),
                              getattr(shape, "lt", None)) if b is not None]  # fmt: skip
        assert any(str(b) in message for b in bounds), message
        assert not (tmp_path / "out").exists()


def test_a_tuple_of_the_wrong_length_is_refused():
    from rlu.agents.discrete_common import AtariSettings
    from rlu.agents.dt import AtariDT, DTConfig
    from rlu.files import MAX_LAYERS

    with pytest.raises(ConfigError, match="field 'betas' has 1 items; expected exactly 2"):
        DTConfig(betas=(0.9,))
    with pytest.raises(ConfigError, match="field 'betas' has 3 items; expected exactly 2"):
        AtariDT(betas=(0.9, 0.95, 0.99))
    with pytest.raises(ConfigError, match="field 'betas\\[1\\]' is 1.0; expected a number >= 0"):
        DTConfig(betas=(0.9, 1.0))
    with pytest.raises(ConfigError, match="field 'channels' has 0 items"):
        AtariSettings(channels=())
    from rlu.agents.iql import IQLConfig

    with pytest.raises(ConfigError, match=f"field 'hidden_layers' has {MAX_LAYERS + 1} items"):
        IQLConfig(hidden_layers=(8,) * (MAX_LAYERS + 1))


def test_a_whole_float_becomes_an_int_and_a_list_a_tuple():
    from rlu.agents.bc import BCConfig
    from rlu.agents.td3bc import TD3BCConfig

    assert BCConfig(batch_size=1e3).batch_size == 1000
    assert type(BCConfig(batch_size=1e3).batch_size) is int
    assert TD3BCConfig(hidden_layers=[32, 32]).hidden_layers == (32, 32)
    with pytest.raises(ConfigError, match="'batch_size' is a number \\(1.5\\)"):
        BCConfig(batch_size=1.5)
    with pytest.raises(ConfigError, match="'learning_rate' is a string"):
        BCConfig(learning_rate="1e-3")


def test_make_agent_checks_a_config_it_is_given():
    from rlu.agents import make_agent
    from rlu.agents.bc import BCConfig
    from rlu.types import ArraySpec, BoundedSpec

    config = BCConfig(hidden_size=8, num_layers=1, batch_size=4)
    object.__setattr__(config, "learning_rate", -1.0)  # past the check at construction
    obs = {"x": ArraySpec((3,), "float32")}
    act = BoundedSpec((1,), "float32")
    with pytest.raises(ConfigError, match="BCConfig field 'learning_rate' is -1.0"):
        make_agent("bc", obs, act, config=config)


def test_a_composed_settings_field_must_be_its_class():
    from rlu.agents.dqn import DQNConfig

    with pytest.raises(ConfigError, match="DQNConfig field 'atari' is an object"):
        DQNConfig(atari={"batch_size": 0})


def test_run_settings_from_python_a_file_and_a_flag(tmp_path):
    from rlu.training.config import RunSettings, read_config_file
    from rlu.training.train import TrainConfig

    with pytest.raises(ConfigError, match="RunSettings field 'eval_envs' is 5000; expected an "
                       "integer from 1 to 1024"):  # fmt: skip
        RunSettings(eval_envs=5000)
    with pytest.raises(ConfigError, match="TrainConfig field 'seed' is -1"):
        TrainConfig(task="t", agent="bc", dataset="d", seed=-1)
    path = tmp_path / "c.json"
    path.write_text('{"run": {"keep_checkpoints": 1001}}')
    with pytest.raises(FormatError, match=f"{path}: field 'run.keep_checkpoints' is 1001"):
        read_config_file(str(path), TrainConfig)


def test_a_yaml_config_nested_too_deep_is_refused(tmp_path):
    pytest.importorskip("yaml")
    from rlu.files import MAX_DEPTH
    from rlu.training.config import read_config_file
    from rlu.training.train import TrainConfig

    flow = tmp_path / "flow.yaml"
    flow.write_text("overrides:\n  x: " + "[" * (MAX_DEPTH + 5) + "]" * (MAX_DEPTH + 5) + "\n")
    block = tmp_path / "block.yaml"
    block.write_text(
        "".join("  " * i + f"k{i}:\n" for i in range(MAX_DEPTH + 5)) + "  " * 40 + "x: 1\n"
    )
    for path in (flow, block):
        with pytest.raises(FormatError, match=f"{path}: YAML nested deeper than {MAX_DEPTH}"):
            read_config_file(str(path), TrainConfig)
    ok = tmp_path / "ok.yaml"  # as deep as the limit: read
    ok.write_text("overrides:\n  x: " + "[" * (MAX_DEPTH - 2) + "]" * (MAX_DEPTH - 2) + "\n")
    value = read_config_file(str(ok), TrainConfig)["overrides"]["x"]
    for _ in range(MAX_DEPTH - 3):
        (value,) = value
    assert value == []


def _train_cli(tmp_path, *extra: str) -> tuple[int, str]:
    import contextlib
    import io

    from rlu.cli import main

    err = io.StringIO()
    out = tmp_path / "runs" / "a" / "run"
    with contextlib.redirect_stderr(err):
        try:
            argv = ["train", "--task", "control_suite/cartpole_swingup", "--agent", "d4pg",
                    "--dataset", str(tmp_path / "no-data"), "--out", str(out)]  # fmt: skip
            code = main([*argv, *extra])
        except SystemExit as stop:
            code = int(stop.code)
    assert not (tmp_path / "runs").exists()  # no run folder, nor its parent (the lock's)
    return code, err.getvalue()


def test_a_boolean_override_reads_the_words_a_yaml_config_reads(tmp_path):
    """``recurrent=true`` on the command line (refused: "a string ('true'); expected true or
    false") is a boolean, as ``recurrent: true`` in a YAML config is; junk is still refused."""
    from rlu.commands._options import YAML_BOOLEANS, parse_overrides

    for word, value in YAML_BOOLEANS.items():
        assert parse_overrides([f"recurrent={word}"]) == {"recurrent": value}
    for junk in ("maybe", "tRUE", "y", "1", "0", "'true'", ""):
        assert not isinstance(parse_overrides([f"recurrent={junk}"])["recurrent"], bool), junk
    yaml = pytest.importorskip("yaml")
    for word, value in YAML_BOOLEANS.items():  # the reader's own spellings, no more
        assert yaml.safe_load(f"x: {word}") == {"x": value}, word
    words = ("true", "false", "yes", "no", "on", "off", "y", "n", "t", "f")
    for word in {v for w in words for v in (w, w.title(), w.upper(), w.swapcase().title())}:
        read = yaml.safe_load(f"x: {word}")["x"]
        assert (word in YAML_BOOLEANS) == isinstance(read, bool), word  # every one, no more

    import contextlib
    import io

    from rlu.cli import main

    argv = ["--agent", "bc", "--task", "control_suite/cartpole_swingup"]
    for word in ("true", "false", "yes", "OFF"):
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            code = main(["train", *argv, "--dataset", str(tmp_path / "no-data"),
                         "--out", str(tmp_path / "run"), f"recurrent={word}"])  # fmt: skip
        # taken: the run goes on to open its data (missing here)
        assert code == 2 and "recurrent" not in err.getvalue(), err.getvalue()
        assert "no-data" in err.getvalue(), err.getvalue()
    code, err = _train_cli(tmp_path, *argv, "recurrent=maybe")
    assert code == 2
    assert "agent 'bc' config field 'recurrent' is a string ('maybe'); expected true or " \
           "false (override recurrent='maybe')" in err  # fmt: skip
    code, err = _train_cli(tmp_path, *argv, "recurrent=1")
    assert code == 2 and "field 'recurrent' is an integer (1); expected true or false" in err


def test_rlu_train_refuses_a_bad_override_before_any_folder_exists(tmp_path):
    code, err = _train_cli(tmp_path, "gamma=1.5")
    assert code == 2
    assert "the command line: agent 'd4pg' config field 'gamma' is 1.5; expected a number " \
           "from 0.0 to 1.0 (override gamma=1.5)" in err  # fmt: skip
    config = tmp_path / "c.yaml"
    config.write_text("overrides:\n  policy_lr: 0.0\n  batch_size: 256\n")
    code, err = _train_cli(tmp_path, "--config", str(config))
    assert code == 2
    assert f"{config}: overrides.policy_lr: agent 'd4pg' config field 'policy_lr' is 0.0; " \
           "expected a number > 0.0 and <= 10.0" in err  # fmt: skip
    config.write_text("overrides:\n  gama: 0.9\n")
    code, err = _train_cli(tmp_path, "--config", str(config))
    assert f"{config}: overrides.gama: agent 'd4pg' config has no field 'gama'" in err
    code, err = _train_cli(tmp_path, "--eval-envs", "0")
    assert code == 2 and "--eval-envs: 0 is out of range" in err


def test_train_refuses_a_bad_override_before_any_folder_exists(tmp_path):
    from rlu.training.train import TrainConfig, train

    config = TrainConfig(task="atari/Pong", agent="dqn", dataset=str(tmp_path / "no-data"),
                         overrides={"atari.n_step": 0})  # fmt: skip
    with pytest.raises(ConfigError, match="config field 'n_step' is 0"):
        train(config, tmp_path / "runs" / "run")
    assert not (tmp_path / "runs").exists()


def test_config_error_is_an_rlu_error_in_the_public_types():
    import rlu.types

    assert issubclass(ConfigError, RluError)
    assert "ConfigError" in rlu.types.__all__


def test_a_sweep_grid_point_out_of_bounds_is_refused_before_the_sweep_folder(tmp_path):
    from rlu.data.bundled import bundled_dataset
    from rlu.training.sweep import SweepConfig, sweep

    task = "control_suite/cartpole_swingup"
    config = SweepConfig(tasks=(task,), agents=("d4pg",), datasets={task: str(bundled_dataset())},
                         grid={"gamma": [0.9, 2.0]})  # fmt: skip
    with pytest.raises(ConfigError, match=f"sweep grid of d4pg on {task}: agent 'd4pg' config "
                       "field 'gamma' is 2.0; expected a number from 0.0 to 1.0"):  # fmt: skip
        sweep(config, tmp_path / "sweep")
    assert not (tmp_path / "sweep").exists()


def test_numpy_numbers_from_code_become_python_numbers():
    import numpy as np

    from rlu.agents.bc import BCConfig
    from rlu.agents.td3bc import TD3BCConfig

    config = BCConfig(batch_size=np.int64(64), learning_rate=np.float32(0.5))
    assert type(config.batch_size) is int and config.batch_size == 64
    assert type(config.learning_rate) is float and config.learning_rate == 0.5
    assert TD3BCConfig(hidden_layers=[np.int64(8), 8]).hidden_layers == (8, 8)
    with pytest.raises(ConfigError, match="'batch_size' is 0"):
        BCConfig(batch_size=np.int32(0))


def test_train_config_from_file_names_the_file_and_key_of_a_bad_override(tmp_path):
    pytest.importorskip("yaml")
    from rlu.training.train import TrainConfig

    path = tmp_path / "bc.yaml"
    path.write_text("task: control_suite/cartpole_swingup\nagent: bc\ndataset: d\n"
                    "overrides:\n  batch_size: 256\n  num_layers: 65\n")  # fmt: skip
    with pytest.raises(ConfigError, match=f"{path}: overrides.num_layers: agent 'bc' config "
                       "field 'num_layers' is 65; expected an integer from 1 to 64"):  # fmt: skip
        TrainConfig.from_file(path)
    ok = TrainConfig.from_file(path, overrides={"num_layers": 4})
    assert ok.overrides == {"num_layers": 4}


def test_every_scale_of_every_generated_task_lies_inside_the_bounds():
    """Each task's behaviour runs at each scale (rlu.generate.scales) are OnlineConfigs inside
    their bounds, and their run counts inside GenerateConfig's."""
    from rlu.generate.config import MAX_RUNS, SCALES
    from rlu.generate.scales import get_scale
    from rlu.tasks import TASKS

    built = 0
    for task in TASKS.values():
        if task.domain not in ("control_suite", "rwrl", "atari"):
            continue  # locomotion records a policy (--policy), DMLab ships data only
        for scale in SCALES:
            s = get_scale(task, scale)
            check_fields(s.online)
            assert 1 <= s.runs <= MAX_RUNS
            built += 1
    assert built > 30
