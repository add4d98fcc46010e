"""The recipe's scales: how many runs, how long, and the behaviour agent's online settings.

``tiny`` is for tests and smoke runs (seconds), ``small`` for minutes on a laptop, ``paper`` the
paper's budgets (clusters). One ``Scale`` per domain and scale name; the RWRL recipe trains the
control suite's D4PG at the same scale.
"""

from __future__ import annotations

from dataclasses import dataclass

from rlu.generate.online import OnlineConfig
from rlu.tasks import TaskSpec
from rlu.types import RluError

SCALES = ("tiny", "small", "paper")

_TINY_D4PG = {"policy_layers": (32, 32), "critic_layers": (32, 32), "batch_size": 32}
_TINY_DQN = {"channels": (8, 16, 16), "hidden_size": 32, "batch_size": 16}


@dataclass(frozen=True)
class Scale:
    """One scale of the recipe for one domain."""

    runs: int
    """Independent training runs (the paper: 3 for the control suite, 5 for Atari)."""
    online: OnlineConfig
    """Each run's behaviour agent and budget."""
    target_episodes: int | None
    """Episodes kept after selection; None: the paper's count for the task."""


def _scales(domain: str) -> dict[str, Scale]:
    if domain in ("control_suite", "rwrl"):
        return {
            # seconds: for tests and smoke runs; tiny networks, learning barely starts
            "tiny": Scale(2, OnlineConfig("d4pg", episodes=2, agent_overrides=_TINY_D4PG,
                                          replay_capacity=5_000, min_replay=500, update_every=16,
                                          checkpoint_steps=1_000, chunk_episodes=1), None),
            # minutes on a laptop: the small D4PG preset, 3 runs of 30 episodes (90K steps)
            "small": Scale(3, OnlineConfig("d4pg", episodes=30, replay_capacity=100_000,
                                           min_replay=2_000, update_every=8,
                                           checkpoint_steps=10_000, chunk_episodes=5), None),
            # the paper's: Acme's D4PG, 3 runs of 1M steps each
            "paper": Scale(3, OnlineConfig("d4pg", episodes=1_000, preset="paper",
                                           replay_capacity=1_000_000, min_replay=10_000,
                                           update_every=8, checkpoint_steps=100_000,
                                           chunk_episodes=20), None),
        }  # fmt: skip
    if domain == "atari":
        return {
            "tiny": Scale(1, OnlineConfig("dqn", episodes=2, agent_overrides=_TINY_DQN,
                                          replay_capacity=2_000, min_replay=50, update_every=4,
                                          epsilon_decay_steps=1_000, checkpoint_steps=100,
                                          chunk_episodes=1,
                                          env_settings={"max_episode_steps": 100}), None),
            "small": Scale(2, OnlineConfig("dqn", episodes=10_000, env_steps=50_000,
                                           replay_capacity=50_000, min_replay=5_000,
                                           update_every=4, epsilon_decay_steps=25_000,
                                           checkpoint_steps=10_000, chunk_episodes=5), None),
            # Dopamine's DQN: 50M agent steps per run, 1M replay, 1M-step checkpoints
            "paper": Scale(5, OnlineConfig("dqn", episodes=10**9, env_steps=50_000_000,
                                           preset="paper", replay_capacity=1_000_000,
                                           min_replay=20_000, update_every=4,
                                           epsilon_decay_steps=250_000,
                                           checkpoint_steps=1_000_000, chunk_episodes=50), None),
        }  # fmt: skip
    raise RluError(
        f"rlu generate trains behaviour agents for the control_suite, atari and rwrl domains; "
        f"{domain!r} is not one of them (locomotion: record your own policy with --policy)"
    )


def check_scale(scale: str) -> None:
    if scale not in SCALES:
        raise RluError(f"unknown --scale {scale!r}; use one of {', '.join(SCALES)}")


def get_scale(task: TaskSpec, scale: str) -> Scale:
    check_scale(scale)
    return _scales(task.domain)[scale]
