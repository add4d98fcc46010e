"""The recipe's scales: Atari's behaviour runs are Dopamine's online DQN with dqn.gin's settings."""

from __future__ import annotations

import pytest

from rlu.generate.scales import get_scale
from rlu.tasks import get_task


def dopamine_epsilon(step: int, decay_period: int = 250_000, epsilon: float = 0.01) -> float:
    """Dopamine's linearly_decaying_epsilon (dqn_agent.py), counted from the first step."""
    bonus = (1.0 - epsilon) * (decay_period - step) / decay_period
    return epsilon + min(max(bonus, 0.0), 1.0 - epsilon)


@pytest.mark.parametrize("scale", ["laptop", "paper"])
def test_atari_scales_run_dopamines_dqn_with_its_online_settings(scale):
    pytest.importorskip("torch")
    from rlu.agents import make_config

    online = get_scale(get_task("atari/Pong"), scale).online
    assert online.agent == "dopamine_dqn" and online.preset == "paper"
    assert (online.min_replay, online.update_every) == (20_000, 4)
    assert online.epsilon_decay_steps == 250_000
    config = make_config(online.agent, True, online.preset, **online.agent_overrides)
    assert config.atari.target_update_period * online.update_every == 8_000  # agent steps
    # a uniform action: the loop's epsilon, else act(greedy=False) with the agent's own epsilon
    for step in (0, 1, 20_000, 125_000, 249_999, 250_000, 400_000):
        frac = min(1.0, step / online.epsilon_decay_steps)
        loop = 1.0 + frac * (online.epsilon_end - 1.0)
        uniform = loop + (1.0 - loop) * config.atari.explore_epsilon
        assert uniform == pytest.approx(dopamine_epsilon(step), rel=1e-12)


def test_atari_paper_scale_is_the_dqn_replay_runs():
    scale = get_scale(get_task("atari/Pong"), "paper")
    assert scale.runs == 5  # five runs per game (Agarwal et al. 2020)
    assert scale.online.env_steps == 50_000_000  # dqn.gin: 200 iterations x 250k agent steps
    assert scale.online.replay_capacity == 1_000_000  # dqn.gin: replay_capacity = 1000000
