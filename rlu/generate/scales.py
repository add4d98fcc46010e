"""The recipe's scales: how many runs, how long, and the behaviour agent's online settings.

``tiny`` is for tests and smoke runs (seconds); ``laptop``, the default, makes the control suite's
behaviour runs reach the paper's behaviour level in minutes of CPU (``LAPTOP``, measured: the
README's generation section); ``paper`` is the paper's budgets (clusters). One ``Scale`` per task
and scale name: the agent a domain's runs train at each scale is its entry's ``behaviour_agents``
(``rlu.domains``), that agent's settings at that scale are :data:`BEHAVIOUR`'s. The RWRL recipe
trains the control suite's D4PG at the same scale, except at ``paper``, where it trains the
paper's RWRL behaviour agent, distributional MPO (``dmpo``, with Acme's settings:
``_PAPER_DMPO``). Atari's behaviour agent is Dopamine's online DQN (``dopamine_dqn``) at every
scale, with Dopamine's online settings at ``laptop`` and ``paper`` (``_DOPAMINE_ONLINE``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from rlu.domains import DOMAINS
from rlu.generate.config import SCALES
from rlu.generate.online import OnlineConfig
from rlu.tasks import TaskSpec
from rlu.types import RluError

_TINY_D4PG = {"policy_layers": (32, 32), "critic_layers": (32, 32), "batch_size": 32}
_TINY_DQN = {"atari.channels": (8, 16, 16), "atari.hidden_size": 32, "atari.batch_size": 16}

# Atari's behaviour agent is Dopamine's online DQN (``dopamine_dqn``: its learner settings are the
# agent's presets, with their sources; Agarwal et al. 2020 generated the DQN Replay data with it).
# The online loop's settings below come from Dopamine's ``dqn.gin`` (google/dopamine,
# dopamine/agents/dqn/configs/dqn.gin), in agent steps:
_DOPAMINE_ONLINE: dict[str, Any] = dict(
    min_replay=20_000,  # DQNAgent.min_replay_history = 20000
    update_every=4,  # DQNAgent.update_period = 4
    epsilon_decay_steps=250_000,  # DQNAgent.epsilon_decay_period = 250000
    # The loop's epsilon decays 1 -> 0 and, when it does not explore, calls act(greedy=False),
    # which adds the agent's own epsilon_train (DQNAgent.epsilon_train = 0.01): a uniform action
    # with probability (1 - f) + f * 0.01 = 1 - 0.99 f after a fraction f of the decay, Dopamine's
    # linear 1 -> 0.01 exactly (the loop's default 0.01 would end at 0.0199).
    epsilon_end=0.0,
)


@dataclass(frozen=True)
class Scale:
    """One scale of the recipe for one task."""

    runs: int
    """Independent training runs (the paper: 3 for the control suite, 5 for Atari)."""
    online: OnlineConfig
    """Each run's behaviour agent and budget."""
    target_episodes: int | None
    """Episodes kept after selection; None: the paper's count for the task."""


@dataclass(frozen=True)
class LaptopTask:
    episodes: int
    """Episodes per run: enough for every run to pass ``target`` (measured, with a margin)."""
    target: float | None
    """The behaviour level a run reaches (its best 10-episode mean return, exploration noise
    included): the level the paper's behaviour runs pass (its D4PG solves these tasks)."""


# Per control-suite task (also the RWRL tasks of the same name): 1000-step episodes per run,
# measured so that each of seed 0's three runs passed the target (cartpole swingup: two of the
# three since the seeds are rlu.types' streams, the third reached 717); the README's generation
# section has where each run passed it, and bench/README.md what a run costs.
LAPTOP = {
    "cartpole_swingup": LaptopTask(60, 800.0),
    "walker_stand": LaptopTask(100, 900.0),
    "walker_walk": LaptopTask(150, 900.0),
    # the hard three: as many episodes as an hour of a 2-core laptop allows
    "cheetah_run": LaptopTask(400, 600.0),
    "finger_turn_hard": LaptopTask(400, 700.0),
    "fish_swim": LaptopTask(400, 600.0),
}
LAPTOP_DEFAULT = LaptopTask(100, None)

# D4PG's small preset (256x256 LayerNorm MLPs, Adam 3e-4, 51 atoms on [-100, 100], hard target
# updates every 100 learner steps) with these changes; the README's generation section has the
# measurements behind each.
_LAPTOP_D4PG = {
    # 3-step targets: cartpole's 10-episode mean passed 800 at episode 34 (5-step: 33; 1-step:
    # 850 at episode 48, the measurement this scale started from)
    "n_step": 3,
    # half the small preset's 256: about the same return per env step on cartpole (600 at
    # episode 25, 256: 28) for 41% of an update's time alone, 68% of a run's CPU under load
    "batch_size": 128,
    # rlu's earlier initialisation (torch's default, the last policy layer times 1e-4): the
    # bundled dataset was made with it, so its recorded command reproduces it
    "init": "torch",
}


def _laptop_online(task: TaskSpec) -> OnlineConfig:
    episodes = LAPTOP.get(task.id.split("/", 1)[1], LAPTOP_DEFAULT).episodes
    return OnlineConfig(
        "d4pg",
        episodes=episodes,
        agent_overrides=_LAPTOP_D4PG,
        # the whole run (an episode takes episode_length + 1 rows): nothing is ever dropped, and
        # the saved replay is no larger than the run
        replay_capacity=episodes * (task.episode_length + 1),
        min_replay=2_000,  # two episodes of the near-zero initial policy plus noise
        # one update per 2 env steps (64 samples per insert; Acme's default 32): the least CPU
        # to a level, measured: walker walk 900 in 410 s of CPU (1 per step: 496 s, 1 per 4:
        # not reached, 600 in 329 s against 262 s), cartpole 800 in 178 s (1 per step: > 200 s)
        update_every=2,
        sigma=0.3,  # Acme's behaviour noise, unchanged: the recorded episodes carry it
        checkpoint_steps=10_000,
        chunk_episodes=10,  # a crash loses at most 10 episodes (each save writes the replay)
    )


def behaviour_target(task: TaskSpec) -> float | None:
    """The return a run's best 10-episode mean should reach at the laptop scale (None: none
    set for this task)."""
    if DOMAINS[task.domain].behaviour_agents.get("laptop") != "d4pg":
        return None  # the targets are D4PG's laptop runs'
    return LAPTOP.get(task.id.split("/", 1)[1], LAPTOP_DEFAULT).target


# The paper's RWRL behaviour agent: distributional MPO with Acme's TF DMPO defaults (the agent's
# ``paper`` preset; acme/agents/tf/dmpo/agent.py: min_replay_size 1000, max_replay_size 1M,
# samples_per_insert 32 at batch 256, i.e. one update per 8 env steps), sampling its own Gaussian
# policy to explore (sigma=None), 3 runs of 1M steps as D4PG's.
_PAPER_DMPO = OnlineConfig(
    "dmpo",
    episodes=1_000,
    preset="paper",
    replay_capacity=1_000_000,
    min_replay=1_000,
    update_every=8,
    sigma=None,
    checkpoint_steps=100_000,
    chunk_episodes=20,
)


def _d4pg_tiny(task: TaskSpec) -> Scale:
    # seconds: for tests and smoke runs; tiny networks, learning barely starts
    return Scale(
        2,
        OnlineConfig(
            "d4pg",
            episodes=2,
            agent_overrides=_TINY_D4PG,
            replay_capacity=5_000,
            min_replay=500,
            update_every=16,
            checkpoint_steps=1_000,
            chunk_episodes=1,
        ),
        None,
    )


def _d4pg_laptop(task: TaskSpec) -> Scale:
    # minutes on a laptop: the paper's 3 runs, each to the paper's behaviour level
    return Scale(3, _laptop_online(task), None)


def _d4pg_paper(task: TaskSpec) -> Scale:
    # the paper's: Acme's D4PG, 3 runs of 1M steps each
    return Scale(
        3,
        OnlineConfig(
            "d4pg",
            episodes=1_000,
            preset="paper",
            replay_capacity=1_000_000,
            min_replay=10_000,
            update_every=8,
            checkpoint_steps=100_000,
            chunk_episodes=20,
        ),
        None,
    )


def _dmpo_paper(task: TaskSpec) -> Scale:
    # the paper's own RWRL behaviour agent at the paper's scale
    return Scale(3, _PAPER_DMPO, None)


def _dqn_tiny(task: TaskSpec) -> Scale:
    # seconds: Dopamine's DQN with tiny networks, 2 episodes of 100 steps, learning at once
    return Scale(
        1,
        OnlineConfig(
            "dopamine_dqn",
            episodes=2,
            agent_overrides=_TINY_DQN,
            replay_capacity=2_000,
            min_replay=50,
            update_every=4,
            epsilon_end=0.0,
            epsilon_decay_steps=1_000,
            checkpoint_steps=100,
            chunk_episodes=1,
            env_settings={"max_episode_steps": 100},
        ),
        None,
    )


def _dqn_laptop(task: TaskSpec) -> Scale:
    # Dopamine's DQN and online settings for 2 of its 250k-step iterations per run: the epsilon
    # decay ends at 250k, the second half acts at 0.01 (far from DQN's level, which takes
    # millions of steps); about 1.5 h of one core per run (bench/README.md).
    return Scale(
        2,
        OnlineConfig(
            "dopamine_dqn",
            episodes=10**6,
            env_steps=500_000,
            preset="paper",
            **_DOPAMINE_ONLINE,
            # a tenth of Dopamine's 1M: 0.7 GB of frames per run, saved with each chunk
            replay_capacity=100_000,
            checkpoint_steps=50_000,
            chunk_episodes=20,
        ),
        None,
    )


def _dqn_paper(task: TaskSpec) -> Scale:
    # Agarwal et al.'s DQN Replay runs: 5 runs x 50M agent steps (dqn.gin's 200 iterations of
    # 250k), Dopamine's 1M replay, a checkpoint per 1M steps as in the release
    return Scale(
        5,
        OnlineConfig(
            "dopamine_dqn",
            episodes=10**9,
            env_steps=50_000_000,
            preset="paper",
            **_DOPAMINE_ONLINE,
            replay_capacity=1_000_000,
            checkpoint_steps=1_000_000,
            chunk_episodes=50,
        ),
        None,
    )


BEHAVIOUR: Mapping[tuple[str, str], Callable[[TaskSpec], Scale]] = MappingProxyType(
    {
        ("d4pg", "tiny"): _d4pg_tiny,
        ("d4pg", "laptop"): _d4pg_laptop,
        ("d4pg", "paper"): _d4pg_paper,
        ("dmpo", "paper"): _dmpo_paper,
        ("dopamine_dqn", "tiny"): _dqn_tiny,
        ("dopamine_dqn", "laptop"): _dqn_laptop,
        ("dopamine_dqn", "paper"): _dqn_paper,
    }
)
"""(behaviour agent, scale) -> the task's Scale: what a domain's ``behaviour_agents``
(``rlu.domains``) name."""


def check_scale(scale: str) -> None:
    if scale not in SCALES:
        raise RluError(f"unknown --scale {scale!r}; use one of {', '.join(SCALES)}")


def get_scale(task: TaskSpec, scale: str) -> Scale:
    check_scale(scale)
    agents = DOMAINS[task.domain].behaviour_agents
    if not agents:
        trained = [d for d, e in DOMAINS.items() if e.behaviour_agents]
        named = ", ".join(trained[:-1]) + f" and {trained[-1]}" if len(trained) > 1 else trained[0]
        policy = ", ".join(d for d, e in DOMAINS.items() if e.generation == "policy")
        raise RluError(
            f"rlu generate trains behaviour agents for the {named} domains; {task.domain!r} is "
            f"not one of them ({policy}: record your own policy with --policy)"
        )
    return BEHAVIOUR[(agents[scale], scale)](task)
