"""Atari 2600 (paper table 3): 46 games, five DQN runs each, transitions and ordered episodes.

Games and selection split: the paper's table 3; minimal action-set sizes: read from ale-py 0.12.1
(``tests/test_tasks.py`` re-checks them against ALE when the ``atari`` extra is installed);
release paths and shard counts: the original ``rl_unplugged/atari.py`` and TFDS ``rlu_atari*``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING

from rlu.domains import Domain
from rlu.domains.paper import EPISODES, SEEDS, PaperConditions, Statement
from rlu.types import ArraySpec

if TYPE_CHECKING:  # pragma: no cover
    from rlu.domains.spec import TaskRef, TaskSpec

NAME = "atari"

ATARI_FRAME_STACK = 4
ATARI_OBSERVATION = ArraySpec((84, 84, ATARI_FRAME_STACK), "uint8")
# 108K frames at frame skip 4 (the paper's / Dopamine's convention); rlu.envs documents the
# original evaluation wrapper's 108,000-agent-step variant.
ATARI_MAX_AGENT_STEPS = 27_000

ATARI_ONLINE = (
    "BeamRider",
    "DemonAttack",
    "DoubleDunk",
    "IceHockey",
    "MsPacman",
    "Pooyan",
    "RoadRunner",
    "Robotank",
    "Zaxxon",
)
ATARI_OFFLINE = (
    "Alien",
    "Amidar",
    "Assault",
    "Asterix",
    "Atlantis",
    "BankHeist",
    "BattleZone",
    "Boxing",
    "Breakout",
    "Carnival",
    "Centipede",
    "ChopperCommand",
    "CrazyClimber",
    "Enduro",
    "FishingDerby",
    "Freeway",
    "Frostbite",
    "Gopher",
    "Gravitar",
    "Hero",
    "Jamesbond",
    "Kangaroo",
    "Krull",
    "KungFuMaster",
    "NameThisGame",
    "Phoenix",
    "Pong",
    "Qbert",
    "Riverraid",
    "Seaquest",
    "SpaceInvaders",
    "StarGunner",
    "TimePilot",
    "UpNDown",
    "VideoPinball",
    "WizardOfWor",
    "YarsRevenge",
)
ATARI_RUNS = tuple(f"run_{r}" for r in range(1, 6))
# atari_episodes_ordered has 49 checkpoint shards for these games, 50 for the others.
_ATARI_49_SHARDS = frozenset({"Carnival", "Gravitar", "StarGunner"})
# Minimal action-set sizes (ale-py 0.12.1, full_action_space=False).
ATARI_NUM_ACTIONS: Mapping[str, int] = MappingProxyType(
    {
        "Alien": 18,
        "Amidar": 10,
        "Assault": 7,
        "Asterix": 9,
        "Atlantis": 4,
        "BankHeist": 18,
        "BattleZone": 18,
        "BeamRider": 9,
        "Boxing": 18,
        "Breakout": 4,
        "Carnival": 6,
        "Centipede": 18,
        "ChopperCommand": 18,
        "CrazyClimber": 9,
        "DemonAttack": 6,
        "DoubleDunk": 18,
        "Enduro": 9,
        "FishingDerby": 18,
        "Freeway": 3,
        "Frostbite": 18,
        "Gopher": 8,
        "Gravitar": 18,
        "Hero": 18,
        "IceHockey": 18,
        "Jamesbond": 18,
        "Kangaroo": 18,
        "Krull": 18,
        "KungFuMaster": 14,
        "MsPacman": 9,
        "NameThisGame": 6,
        "Phoenix": 8,
        "Pong": 6,
        "Pooyan": 6,
        "Qbert": 6,
        "Riverraid": 18,
        "RoadRunner": 18,
        "Robotank": 18,
        "Seaquest": 18,
        "SpaceInvaders": 6,
        "StarGunner": 18,
        "TimePilot": 10,
        "UpNDown": 6,
        "VideoPinball": 9,
        "WizardOfWor": 10,
        "YarsRevenge": 18,
        "Zaxxon": 18,
    }
)


_TFDS_ATARI = re.compile(r"^(?P<game>[A-Za-z]+)_run_(?P<run>\d+)$")


def build_tasks() -> list[TaskSpec]:
    """The Atari TaskSpecs."""
    from rlu.domains.spec import ReleaseDataset, TaskSpec
    from rlu.types import DiscreteSpec

    tasks = []
    for game in ATARI_ONLINE + ATARI_OFFLINE:
        n_ordered = 49 if game in _ATARI_49_SHARDS else 50
        tasks.append(
            TaskSpec(
                id=f"{NAME}/{game}",
                domain=NAME,
                name=game,
                observation_spec=ATARI_OBSERVATION,
                action_spec=DiscreteSpec((), "int64", ATARI_NUM_ACTIONS[game]),
                episode_length=ATARI_MAX_AGENT_STEPS,
                selection="online" if game in ATARI_ONLINE else "offline",
                # 50M transitions per run; episodes vary per run and are not a paper number.
                episodes=MappingProxyType({}),
                release=(
                    ReleaseDataset("atari", f"atari/{game}/{{run}}", {r: 100 for r in ATARI_RUNS}),
                    ReleaseDataset(
                        "atari_episodes_ordered",
                        f"atari_episodes_ordered/{game}/{{run}}",
                        {r: n_ordered for r in ATARI_RUNS},
                    ),
                ),
                env=MappingProxyType({"game": game}),
                datasets=ATARI_RUNS,
            )
        )
    return tasks


def tfds_ref(
    tasks: Mapping[str, TaskSpec], name: str, builder: str, config: str, family: str, fix: str
) -> TaskRef:
    """``rlu_atari/<Game>_run_<N>``: the game's task and run."""
    from rlu.domains.spec import TaskRef
    from rlu.types import RluError

    m = _TFDS_ATARI.match(config)
    games = {t.name.lower(): t for t in tasks.values() if t.domain == NAME}
    task = games.get(m["game"].lower()) if m else None
    run = f"run_{m['run']}" if m else ""
    if task is None or run not in task.datasets:
        raise RluError(f"{name!r}: {builder} has no config {config!r}; {fix}")
    return TaskRef(task, name, family=family, run=run)


# Appendix A.2, table 'Atari experiments hyperparameters': "Training Steps: 2M learning steps",
# on a fixed replay memory of 2M steps of the release.
PAPER_STEPS = 2_000_000
PAPER_CONDITIONS = PaperConditions(
    MappingProxyType(
        {
            "preset": Statement(
                "the Atari baselines' settings",
                "appendix A.2 and its table 'Atari experiments hyperparameters'",
            ),
            "budget": Statement(
                PAPER_STEPS,
                "appendix A.2, table 'Atari experiments hyperparameters': 'Training Steps: 2M "
                "learning steps'",
            ),
            "data": Statement(
                PAPER_STEPS,
                "appendix A.2, table 'Atari experiments hyperparameters': a fixed replay memory "
                "of 2M steps (which 2M of the release's it does not say)",
            ),
            "episodes": EPISODES,
            "seeds": SEEDS,
            "selection": Statement(
                "online policy selection per game over the grid; naive offline selection: the "
                "configuration with the best median over the tuning games",
                "section 2.2 and section 4 ('Naive approach for offline policy selection')",
            ),
        }
    ),
    replay_steps=PAPER_STEPS,
    discrete_agents=True,
)
"""What the paper states of the conditions of its Atari numbers (appendix A.2)."""

DOMAIN = Domain(
    name=NAME,
    title="Atari 2600",
    build_tasks=build_tasks,
    env_module="rlu.domains.atari.env",
    release_module="rlu.domains.atari.release",
    extra="atari",
    packages=("ale_py", "cv2", "gymnasium"),
    datasets="runs",
    step_limit_setting="max_episode_steps",
    vector_backend="ale",
    native_vector="ale",
    tfds_builders=MappingProxyType(
        {
            "rlu_atari": "atari_episodes_ordered",
            "rlu_atari_checkpoints_ordered": "atari_episodes_ordered",
        }
    ),
    tfds_examples=MappingProxyType(
        {
            "rlu_atari": "rlu_atari/Pong_run_1",
            "rlu_atari_checkpoints_ordered": "rlu_atari_checkpoints_ordered/Pong_run_1",
        }
    ),
    tfds_ref=tfds_ref,
    paper_table="appendix D, table 'Atari 2600 results'",
    statistic="median",
    paper_conditions=PAPER_CONDITIONS,
    normalised=True,
    # the paper draws Atari normalised: the median over games (its Atari figure), the per-game
    # improvement (appendix) and the IQN and BCQ ablations (appendix)
    report_figures=("atari_median", "atari_per_game", "iqn_tau", "bcq_threshold"),
    stacked_frames=True,
    generation="runs",
    success="none",
    sim_packages=("ale-py",),
    # Dopamine's online DQN at every scale (rlu.generate.scales)
    behaviour_agents=MappingProxyType(
        {"tiny": "dopamine_dqn", "laptop": "dopamine_dqn", "paper": "dopamine_dqn"}
    ),
)
