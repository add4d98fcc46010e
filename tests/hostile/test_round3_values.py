"""Configured values out of range (issue 39, third round, item 2): refused where the agent
config is built from overrides, from the fields' bounds (``rlu.files.bounds`` metadata), before
torch sees them; a config file's run steps beyond ``rlu.files.MAX_STEPS``."""

from __future__ import annotations

import pytest

from rlu.types import RluError

pytest.importorskip("torch")


@pytest.mark.parametrize(
    ("agent", "discrete", "field", "value"),
    [
        ("bc", False, "hidden_size", -5),
        ("bc", False, "hidden_size", 0),
        ("bc", False, "hidden_size", 100000),
        ("bc", False, "num_layers", 10**9),
        ("bc", False, "learning_rate", -1),
        ("bc", False, "mixture_components", 0),
        ("bc", False, "eval_variance", -1),
        ("dqn", True, "atari.gamma", 1.5),
        ("dqn", True, "atari.gamma", "x"),
        ("dqn", True, "atari.channels", "abc"),
        ("dqn", True, "atari.channels", (32, 0, 64)),
    ],
)
def test_an_out_of_range_override_is_refused(agent, discrete, field, value):
    from rlu.agents import make_config

    with pytest.raises(RluError, match=f"field '{field.split('.')[-1]}"):
        make_config(agent, discrete, "small", **{field: value})


def test_run_steps_beyond_the_limit_are_refused(tmp_path):
    from rlu.training.config import read_config_file
    from rlu.training.train import TrainConfig
    from rlu.types import FormatError

    path = tmp_path / "c.json"
    path.write_text('{"run": {"steps": 10000000000}}')
    with pytest.raises(FormatError, match="run.steps"):
        read_config_file(str(path), TrainConfig)
