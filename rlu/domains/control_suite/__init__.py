"""DM Control Suite (paper table 1): nine dm_control tasks, seq2 windows and episode files.

Observation keys, dims and action dims: the ``shapes`` tables of the original
``rl_unplugged/dm_control_suite.py`` (github.com/deepmind/deepmind-research); selection split and
episode counts: the paper's table 1 (Gulcehre et al. 2020, arXiv:2006.13888).
"""

from __future__ import annotations

import functools
from types import MappingProxyType
from typing import TYPE_CHECKING, Literal

from rlu.domains import Domain
from rlu.domains.common import act, config_task_ref, obs

if TYPE_CHECKING:  # pragma: no cover
    from rlu.domains.spec import TaskSpec

NAME = "control_suite"

CONTROL: dict[str, tuple[dict[str, int], int, int, Literal["online", "offline"]]] = {
    # name: (obs dims in the release's key order, action dim, episodes, selection)
    "cartpole_swingup": (dict(position=3, velocity=2), 1, 40, "online"),
    "cheetah_run": (dict(position=8, velocity=9), 6, 300, "online"),
    "humanoid_run": (
        dict(
            velocity=27,
            com_velocity=3,
            torso_vertical=3,
            extremities=12,
            head_height=1,
            joint_angles=21,
        ),
        21,
        3000,
        "online",
    ),
    "manipulator_insert_ball": (
        dict(arm_pos=16, arm_vel=8, touch=5, hand_pos=4, object_pos=4, object_vel=3, target_pos=4),
        5,
        1500,
        "online",
    ),
    "walker_stand": (dict(orientations=14, velocity=9, height=1), 6, 200, "online"),
    "finger_turn_hard": (
        dict(position=4, velocity=3, touch=2, target_position=2, dist_to_target=1),
        2,
        500,
        "offline",
    ),
    "fish_swim": (dict(target=3, velocity=13, upright=1, joint_angles=7), 5, 200, "offline"),
    "manipulator_insert_peg": (
        dict(arm_pos=16, arm_vel=8, touch=5, hand_pos=4, object_pos=4, object_vel=3, target_pos=4),
        5,
        1500,
        "offline",
    ),
    "walker_walk": (dict(orientations=14, velocity=9, height=1), 6, 200, "offline"),
}


def build_tasks() -> list[TaskSpec]:
    """The control suite's TaskSpecs."""
    from rlu.domains.spec import ReleaseDataset, TaskSpec

    tasks = []
    for name, (dims, adim, n_ep, sel) in CONTROL.items():
        domain, task = name.split("_", 1)
        tasks.append(
            TaskSpec(
                id=f"{NAME}/{name}",
                domain=NAME,
                name=name,
                observation_spec=obs(**dims),
                action_spec=act(adim),
                episode_length=1000,
                selection=sel,
                episodes=MappingProxyType({"": n_ep}),
                release=(
                    ReleaseDataset(
                        "dm_control_suite", f"dm_control_suite/{name}/train", {"": 100}, 2
                    ),
                    ReleaseDataset(
                        "dm_control_suite_episodes",
                        f"dm_control_suite_episodes/{name}/train",
                        {"": 100},
                    ),
                ),
                env=MappingProxyType({"suite_domain": domain, "suite_task": task}),
            )
        )
    return tasks


DOMAIN = Domain(
    name=NAME,
    title="DM Control Suite",
    build_tasks=build_tasks,
    env_module="rlu.domains.control_suite.env",
    release_module="rlu.domains.control_suite.release",
    extra="control",
    packages=("dm_control", "mujoco", "gymnasium"),
    mujoco=True,
    vector_backend="sync",
    tfds_builders=MappingProxyType({"rlu_control_suite": "dm_control_suite_episodes"}),
    tfds_examples=MappingProxyType({"rlu_control_suite": "rlu_control_suite/cartpole_swingup"}),
    tfds_ref=functools.partial(config_task_ref, NAME),
    paper_table="appendix B, table 'DM Control suite results'",
    generation="runs",
    sim_packages=("dm-control", "mujoco"),
    # Acme's D4PG, the paper's behaviour agent, at every scale (rlu.generate.scales)
    behaviour_agents=MappingProxyType({"tiny": "d4pg", "laptop": "d4pg", "paper": "d4pg"}),
)
