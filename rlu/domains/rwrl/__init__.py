"""Real-World RL (paper table 4): four dm_control tasks under the none and easy challenges.

Episode counts: the paper's table 4; shard counts: TFDS ``rlu_rwrl`` ``SHARDS_MAPPING``; paths:
the original ``rl_unplugged/rwrl.py`` and TFDS ``rlu_rwrl.py``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING

from rlu.domains import Domain
from rlu.domains.common import act, f32, obs
from rlu.types import ArraySpec

if TYPE_CHECKING:  # pragma: no cover
    from rlu.domains.spec import TaskRef, TaskSpec

NAME = "rwrl"

# Paper sizes small / medium / large are the TFDS 20% / 40% / 100% datasets (the episode counts
# agree: e.g. cartpole none 100 / 200 / 500). The easy challenge was released at the large size.
RWRL_SIZES = {"small": "20_percent", "medium": "40_percent", "large": "100_percent"}
RWRL_DATASETS = ("none/small", "none/medium", "none/large", "easy/large")
_RWRL = {
    # name: (suite domain, task, obs dims, action dim, episodes small/medium/large,
    #        shards none 20/40/100 %, shards easy 100 %)
    "cartpole_swingup": ("cartpole", "swingup", dict(position=3, velocity=2), 1, (100, 200, 500),
                         (6, 6, 7), 14),
    "walker_walk": ("walker", "walk", dict(orientations=14, height=1, velocity=9), 6,
                    (1000, 2000, 5000), (14, 48, 94), 371),
    "quadruped_walk": ("quadruped", "walk",
                       dict(egocentric_state=44, torso_velocity=3, torso_upright=1, imu=6,
                            force_torque=24), 12, (100, 200, 500), (4, 7, 10), 15),
    "humanoid_walk": ("humanoid", "walk",
                      dict(joint_angles=21, head_height=1, extremities=12, torso_vertical=3,
                           com_velocity=3, velocity=27), 21, (4000, 8000, 20000), (125, 344, 391),
                      769),
}  # fmt: skip
RWRL_EASY_DUMMY_KEYS = tuple(f"dummy-{i}" for i in range(10))
_TFDS_RWRL = re.compile(
    r"^(?P<task>[a-z]+_[a-z]+)_combined_challenge_(?P<challenge>none|easy)_(?P<size>\d+_percent)$"
)


def observation_spec(task: TaskSpec, challenge: str) -> Mapping[str, ArraySpec]:
    """Observation spec of an RWRL task under a challenge (``easy`` adds 10 dummy scalars)."""
    from rlu.types import RluError

    if not isinstance(task.observation_spec, Mapping):
        raise RluError(f"{task.id}: an RWRL task's observation spec is a dict of arrays")
    spec = dict(task.observation_spec)
    if challenge == "easy":
        spec.update({k: f32(1) for k in RWRL_EASY_DUMMY_KEYS})
    elif challenge != "none":
        raise RluError(f"RWRL challenge {challenge!r} is not released; use 'none' or 'easy'")
    return MappingProxyType(spec)


def build_tasks() -> list[TaskSpec]:
    """The RWRL TaskSpecs."""
    from rlu.domains.spec import ReleaseDataset, TaskSpec

    tasks = []
    for name, (sdom, stask, dims, adim, eps, shards_none, shards_easy) in _RWRL.items():
        episodes = {f"none/{s}": n for s, n in zip(RWRL_SIZES, eps, strict=True)}
        episodes["easy/large"] = eps[2]
        shards = {f"none/{s}": n for s, n in zip(RWRL_SIZES, shards_none, strict=True)}
        shards["easy/large"] = shards_easy
        tasks.append(
            TaskSpec(
                id=f"{NAME}/{name}",
                domain=NAME,
                name=name,
                # Challenge `easy` adds the scalar keys dummy-0..dummy-9 (rlu.envs / release
                # reader).
                observation_spec=obs(**dims),
                action_spec=act(adim),
                episode_length=1000,
                selection="online",
                episodes=MappingProxyType(episodes),
                release=(
                    ReleaseDataset(
                        "rwrl",
                        f"rwrl/combined_challenge_{{challenge}}/{sdom}/{stask}/{{size}}/"
                        "episodes.tfrecord",
                        MappingProxyType(shards),
                        folders=MappingProxyType(RWRL_SIZES),
                    ),
                ),
                env=MappingProxyType({"suite_domain": sdom, "suite_task": stask}),
                datasets=RWRL_DATASETS,
            )
        )
    return tasks


def tfds_ref(
    tasks: Mapping[str, TaskSpec], name: str, builder: str, config: str, family: str, fix: str
) -> TaskRef:
    """``rlu_rwrl/<task>_combined_challenge_<none|easy>_<P>_percent``: task, challenge, size."""
    from rlu.domains.spec import TaskRef
    from rlu.types import RluError

    m = _TFDS_RWRL.match(config)
    task = tasks.get(f"{NAME}/{m['task']}") if m else None
    if m is None or task is None:
        raise RluError(f"{name!r}: {builder} has no config {config!r}; {fix}")
    size = {v: k for k, v in RWRL_SIZES.items()}.get(m["size"])
    if size is None or f"{m['challenge']}/{size}" not in task.datasets:
        have = ", ".join(f"{c}_{RWRL_SIZES[z]}" for c, z in (d.split("/") for d in task.datasets))
        raise RluError(
            f"{name!r}: TFDS's {m['challenge']} {m['size']} dataset is not one rlu reads; rlu "
            f"has the paper's RWRL datasets (combined_challenge_...: {have})"
        )
    return TaskRef(task, name, family=family, challenge=m["challenge"], size=size)


DOMAIN = Domain(
    name=NAME,
    title="Real-World RL",
    build_tasks=build_tasks,
    env_module="rlu.domains.rwrl.env",
    release_module="rlu.domains.rwrl.release",
    extra="control",
    packages=("dm_control", "mujoco", "gymnasium"),
    mujoco=True,
    datasets="challenge_size",
    challenges=("none", "easy"),
    vector_backend="sync",
    tfds_builders=MappingProxyType({"rlu_rwrl": "rwrl"}),
    tfds_examples=MappingProxyType(
        {"rlu_rwrl": "rlu_rwrl/walker_walk_combined_challenge_none_100_percent"}
    ),
    tfds_ref=tfds_ref,
    generation="snapshots",
    sim_packages=("dm-control", "mujoco"),
    # the control suite's D4PG below the paper's scale, where the paper's own RWRL behaviour
    # agent, distributional MPO, trains (rlu.generate.scales)
    behaviour_agents=MappingProxyType({"tiny": "d4pg", "laptop": "d4pg", "paper": "dmpo"}),
)
