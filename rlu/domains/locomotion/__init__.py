"""DM Locomotion (paper table 2): humanoid and rodent tasks with the egocentric camera.

Observation keys and dims: the ``shapes`` tables of the original ``rl_unplugged/
dm_control_suite.py``; episode counts, sequence lengths and selection split: the paper's table 2.
"""

from __future__ import annotations

import dataclasses
import functools
from types import MappingProxyType
from typing import TYPE_CHECKING, Literal

from rlu.domains import Domain
from rlu.domains.common import CAMERA, act, config_task_ref, f32
from rlu.domains.paper import CONTINUOUS

if TYPE_CHECKING:  # pragma: no cover
    from rlu.domains.spec import TaskSpec

NAME = "locomotion"

HUMANOID_OBS = dict(
    joints_vel=56,
    sensors_velocimeter=3,
    sensors_gyro=3,
    joints_pos=56,
    world_zaxis=3,
    body_height=1,
    sensors_accelerometer=3,
    end_effectors_pos=12,
)
RODENT_OBS = dict(
    joints_pos=30,
    joints_vel=30,
    tendons_pos=8,
    tendons_vel=8,
    appendages_pos=15,
    world_zaxis=3,
    sensors_accelerometer=3,
    sensors_velocimeter=3,
    sensors_gyro=3,
    sensors_touch=4,
)
LOCOMOTION: dict[str, tuple[str, int, int, int, Literal["online", "offline"], str, int, int]] = {
    # name: (walker, action dim, episodes, paper seq length, selection, release dir, release seq,
    #        episode files name, episode length)
    # The paper lists rodent_bowl_escape with seq 40, but the original loader reads
    # rodent_bowl_escape/seq2; the release path follows the loader (the files), seq_length the
    # paper.
    # Episode lengths are the env's, measured (tests/envs/test_locomotion.py): composer ends an
    # episode once physics time >= the time limit, and for the humanoid 6000 additions of the
    # 0.005 s timestep sum to 29.99999999999 s < 30 s, so its episodes last 1001 steps, not the
    # 30 / 0.03 = 1000 the numbers suggest. The rodents' sums reach 20 s and 30 s on time.
    "humanoid_corridor": ("humanoid", 56, 4000, 2, "online", "humanoid_corridor", 2, 1001),
    "humanoid_walls": ("humanoid", 56, 4000, 40, "online", "humanoid_walls", 40, 1001),
    "rodent_gaps": ("rodent", 38, 2000, 2, "online", "rodent_gaps", 2, 1500),
    "rodent_two_touch": ("rodent", 38, 2000, 40, "online", "rodent_two_touch", 40, 1500),
    "humanoid_gaps": ("humanoid", 56, 4000, 2, "offline", "humanoid_gaps", 2, 1001),
    "rodent_bowl_escape": ("rodent", 38, 2000, 40, "offline", "rodent_bowl_escape", 2, 1000),
    "rodent_mazes": ("rodent", 38, 2000, 40, "offline", "rodent_mazes", 40, 1500),
}

RECURRENT = ("rodent_two_touch", "rodent_bowl_escape", "rodent_mazes")
"""The paper's "tasks of the sequential nature (Rodent Two Tap, Rodent Escape and Rodent
Mazes)", whose networks add two LSTMs (appendix A.1): rlu's ``paper_recurrent`` preset there."""


def build_tasks() -> list[TaskSpec]:
    """The locomotion TaskSpecs."""
    from rlu.domains.spec import ReleaseDataset, TaskSpec

    tasks = []
    for name, (walker, adim, n_ep, seq, sel, rdir, rseq, ep_len) in LOCOMOTION.items():
        dims = HUMANOID_OBS if walker == "humanoid" else RODENT_OBS
        spec = {f"walker/{k}": f32(d) for k, d in dims.items()}
        spec["walker/egocentric_camera"] = CAMERA
        tasks.append(
            TaskSpec(
                id=f"{NAME}/{name}",
                domain=NAME,
                name=name,
                observation_spec=MappingProxyType(spec),
                action_spec=act(adim),
                episode_length=ep_len,
                selection=sel,
                episodes=MappingProxyType({"": n_ep}),
                release=(
                    ReleaseDataset(
                        "dm_locomotion", f"dm_locomotion/{rdir}/seq{rseq}/train", {"": 100}, rseq
                    ),
                    ReleaseDataset(
                        "dm_locomotion_episodes", f"dm_locomotion_episodes/{name}/train", {"": 100}
                    ),
                ),
                env=MappingProxyType({"walker": walker, "builder": name}),
                seq_length=seq,
            )
        )
    return tasks


DOMAIN = Domain(
    name=NAME,
    title="DM Locomotion",
    build_tasks=build_tasks,
    env_module="rlu.domains.locomotion.env",
    release_module="rlu.domains.locomotion.release",
    extra="locomotion",
    packages=("dm_control", "mujoco", "gymnasium"),
    mujoco=True,
    vector_backend="process",
    tfds_builders=MappingProxyType({"rlu_locomotion": "dm_locomotion_episodes"}),
    tfds_examples=MappingProxyType({"rlu_locomotion": "rlu_locomotion/rodent_gaps"}),
    tfds_ref=functools.partial(config_task_ref, NAME),
    paper_table="appendix C, table 'DM Locomotion results'",
    paper_conditions=dataclasses.replace(
        CONTINUOUS, recurrent_tasks=tuple(f"{NAME}/{name}" for name in RECURRENT)
    ),
    camera_setting="camera",
    generation="policy",
    success="time_limit",
    sim_packages=("dm-control", "mujoco"),
)
