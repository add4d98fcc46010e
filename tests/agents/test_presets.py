"""The paper's settings in the presets, what ``greedy`` means per agent, and the config plumbing
(dotted overrides into composed settings, JSON round trips)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rlu.agents import (  # noqa: E402
    AGENTS,
    DISCRETE_AGENTS,
    agent_module,
    config_from_json,
    make_agent,
    make_config,
)
from rlu.agents import discrete_common as dc  # noqa: E402
from rlu.types import RluError  # noqa: E402
from tests.fakes import ATARI_ACTION, ATARI_OBS, CONT_ACTION, IMAGE_OBS, fake_transition  # noqa: E402

TINY = {"atari.channels": (4, 8, 8), "atari.hidden_size": 16}


def test_atari_table_is_every_discrete_paper_preset():
    # dopamine_dqn is the data's online behaviour agent, with Dopamine's settings, not the
    # paper's offline table (tests/agents/test_dqn_online.py checks them); dt is not one of the
    # paper's baselines and has its own paper's settings (tests/agents/test_dt.py), as has r2d2
    # (Kapturowski et al.'s: tests/agents/test_r2d2.py)
    for name in [n for n in DISCRETE_AGENTS if n not in ("dopamine_dqn", "dt", "r2d2")]:
        config = make_config(name, True, "paper")
        atari = config.atari
        assert atari == dc.AtariSettings()
        assert (atari.channels, atari.kernel_sizes, atari.strides) == (
            (32, 64, 64), (8, 4, 3), (4, 2, 1),
        )  # fmt: skip
        assert atari.hidden_size == 512 and atari.batch_size == 256 and atari.adam_eps == 1e-7
        assert atari.gamma == 0.99 and atari.reward_clip == 1.0
        assert atari.eval_epsilon == pytest.approx(0.4**8)
        assert atari.num_steps == 2_000_000
        assert agent_module(name, True).GRID["learning_rate"] == [3e-5, 5e-5, 1e-4]
        if name != "bc":
            assert config.atari.target_update_period == 2500


def test_paper_presets_name_the_paper_choices():
    assert make_config("dqn", True, "paper").double_q is True
    assert make_config("iqn", True, "paper").num_tau_samples == 16
    assert make_config("bcq", True, "paper").threshold == 0.5
    assert make_config("rem", True, "paper").num_heads == 4
    assert make_config("rem", True, "paper").separate_networks is True  # "4 DQN networks"
    assert agent_module("bcq", True).GRID["threshold"] == [0.25, 0.5, 0.75, 1.0]
    assert agent_module("iqn", True).GRID["num_tau_samples"] == [8, 16, 32]
    lrs = {n: make_config(n, True, "paper").learning_rate for n in ("bc", "dqn", "iqn", "bcq",
                                                                     "rem")}  # fmt: skip
    assert lrs == {"bc": 3e-5, "dqn": 3e-5, "iqn": 1e-4, "bcq": 1e-4, "rem": 1e-4}


def test_residual_torso_of_the_paper_presets():
    for name in ("bc", "rabm"):
        agent = make_agent(name, IMAGE_OBS, CONT_ACTION, preset="paper_recurrent")
        mlp = (agent.policy["torso"] if name == "bc" else agent.policy.torso).mlp
        assert len(mlp.blocks) * 2 == 8 and mlp.output_dim == 1024
        assert agent.batch_spec.kind == "sequence" and agent.batch_spec.batch_size == 128


def test_batch_specs_say_what_the_data_must_be():
    d4pg = make_agent("d4pg", IMAGE_OBS, CONT_ACTION, preset="paper")  # the release's windows
    assert d4pg.batch_spec.n_step == 1 and d4pg.batch_spec.gamma == 0.99
    assert d4pg.batch_spec.reward_clip is None
    d4pg = make_agent("d4pg", IMAGE_OBS, CONT_ACTION, preset="paper", n_step=5)
    assert d4pg.batch_spec.n_step == 5 and d4pg.batch_spec.gamma == 0.99
    assert d4pg.batch_spec.bootstrap_gamma == pytest.approx(0.99**5)
    dqn = make_agent("dqn", ATARI_OBS, ATARI_ACTION, "small", **TINY, **{"atari.n_step": 3})
    assert dqn.batch_spec.n_step == 3 and dqn.batch_spec.reward_clip == 1.0
    assert dqn.batch_spec.bootstrap_gamma == pytest.approx(0.99**3)


def test_bc_and_bcq_names_pick_the_variant_from_the_action_spec():
    assert type(make_agent("bc", ATARI_OBS, ATARI_ACTION, **TINY)).__module__ == (
        "rlu.agents.bc_discrete"
    )
    assert type(make_agent("bcq", ATARI_OBS, ATARI_ACTION, **TINY)).__module__ == (
        "rlu.agents.bcq_discrete"
    )
    assert type(make_agent("bc", IMAGE_OBS, CONT_ACTION)).__module__ == "rlu.agents.bc"


def test_greedy_means_what_the_docstrings_say():
    obs = fake_transition(ATARI_OBS, ATARI_ACTION, batch=64, seed=3).observation
    frames = torch.from_numpy(obs)
    no_eps = {"atari.eval_epsilon": 0.0}
    with torch.no_grad():
        # BC: the max action of the policy head
        bc = make_agent("bc", ATARI_OBS, ATARI_ACTION, **TINY, **no_eps)
        np.testing.assert_array_equal(bc.act(obs), bc.network(frames).argmax(-1).numpy())
        # BCQ at threshold 1: only the imitation head's argmax is allowed
        bcq = make_agent("bcq", ATARI_OBS, ATARI_ACTION, **TINY, **no_eps, threshold=1.0)
        _, logits = bcq.network(frames)
        np.testing.assert_array_equal(bcq.act(obs), logits.argmax(-1).numpy())
        # REM: argmax of the mean of the heads
        rem = make_agent("rem", ATARI_OBS, ATARI_ACTION, **TINY, **no_eps)
        np.testing.assert_array_equal(rem.act(obs), rem.network(frames).mean(1).argmax(-1).numpy())
    # epsilon 1 acts uniformly at random
    dqn = make_agent("dqn", ATARI_OBS, ATARI_ACTION, **TINY, **{"atari.eval_epsilon": 1.0})
    counts = np.bincount(dqn.act(np.repeat(obs, 10, axis=0)), minlength=6)
    assert counts.min() > 50


def test_hard_target_updates_follow_the_period():
    dqn = make_agent("dqn", ATARI_OBS, ATARI_ACTION, **TINY, **{"atari.target_update_period": 2})
    batch = fake_transition(ATARI_OBS, ATARI_ACTION, batch=6)

    def same() -> bool:
        return all(
            torch.equal(a, b)
            for a, b in zip(dqn.network.parameters(), dqn.target_network.parameters(), strict=True)
        )

    assert same()
    dqn.update(batch)
    assert not same()
    dqn.update(batch)
    assert same()


def test_dotted_overrides_reach_composed_settings_and_unknown_fields_are_named():
    config = make_config("dqn", True, "small", **{"atari.batch_size": 64}, learning_rate=1e-3)
    assert config.atari.batch_size == 64 and config.learning_rate == 1e-3
    assert config.atari.channels == dc.SMALL.channels  # the rest of the preset stays
    assert make_config("dqn", True, "small", **{"atari.channels": [8, 8, 8]}).atari.channels == (
        8, 8, 8,
    )  # fmt: skip
    with pytest.raises(RluError, match=r"atari\.batch_size"):  # the hint names the path
        make_config("dqn", True, "small", batch_size=64)
    with pytest.raises(RluError, match="no field"):
        make_config("dqn", True, "small", **{"atari.nope": 1})
    with pytest.raises(RluError, match="no preset"):
        make_config("dqn", True, "huge")


@pytest.mark.parametrize(("name", "discrete"), sorted(AGENTS), ids=lambda x: str(x))
def test_configs_survive_json(name, discrete):
    module = agent_module(name, discrete)
    for config in module.PRESETS.values():
        text = json.dumps(dataclasses.asdict(config))
        assert config_from_json(module.Config, json.loads(text)) == config
    with pytest.raises(RluError, match="no field"):
        config_from_json(module.Config, {"no_such_field": 1})
