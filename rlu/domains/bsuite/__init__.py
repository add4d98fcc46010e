"""bsuite (the release's ``bsuite/`` files): catch, cartpole and mountain_car at six noise levels.

Release facts (the original ``rl_unplugged/bsuite.ipynb``; ReinforcementLearning.jl's
``bsuite.jl`` and ``register.jl``): objects ``bsuite/<env>/0_<noise>/<run>_full-00000-of-00001``
(bsuite id index 0, noise 0.0 to 0.5 in steps of 0.1, runs 0 to 4; ``_full_train`` and
``_full_valid`` splits exist beside each, not registered here), GZIP TFRecords of 2-step records
with ``observation`` (float: cartpole 6, mountain_car 3, catch 10x5 = 50, flat), ``action``
(int64), ``reward``, ``discount``, ``episodic_reward`` and ``step_type`` (int64, 2 = LAST). At the
noise level's probability the agent's action was replaced by a uniform random one; the env's
``random_prob`` setting does the same. Observations are kept flat, as the files store them.
Episode lengths are bsuite 0.3.6's defaults (catch: rows - 1 = 9; cartpole and mountain_car:
1000 steps). bsuite has no TensorFlow Datasets builder.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import TYPE_CHECKING

from rlu.domains import Domain
from rlu.domains.common import f32

if TYPE_CHECKING:  # pragma: no cover
    from rlu.domains.spec import TaskSpec

NAME = "bsuite"
NOISE_LEVELS = ("0.0", "0.1", "0.2", "0.3", "0.4", "0.5")
RUNS = tuple(str(k) for k in range(5))
DATASETS = tuple(f"{noise}/{run}" for noise in NOISE_LEVELS for run in RUNS)
"""``NOISE/RUN`` (``0.1/3``): the noise level and the release's run index."""
BSUITE = {
    # name: (bsuite environment class, flat observation size, actions, episode length)
    "catch": ("catch.Catch", 50, 3, 9),
    "cartpole": ("cartpole.Cartpole", 6, 3, 1000),
    "mountain_car": ("mountain_car.MountainCar", 3, 3, 1000),
}


def build_tasks() -> list[TaskSpec]:
    """The bsuite TaskSpecs."""
    from rlu.domains.spec import ReleaseDataset, TaskSpec
    from rlu.types import DiscreteSpec

    tasks = []
    for name, (env_class, size, actions, length) in BSUITE.items():
        tasks.append(
            TaskSpec(
                id=f"{NAME}/{name}",
                domain=NAME,
                name=name,
                observation_spec=f32(size),
                action_spec=DiscreteSpec((), "int64", actions),
                episode_length=length,
                selection="offline",  # bsuite is not in the paper's tables
                episodes=MappingProxyType({}),
                release=(
                    ReleaseDataset(
                        "bsuite", f"bsuite/{name}/0_{{0}}/{{1}}_full", {d: 1 for d in DATASETS}
                    ),
                ),
                env=MappingProxyType({"bsuite_class": env_class}),
                datasets=DATASETS,
            )
        )
    return tasks


DOMAIN = Domain(
    name=NAME,
    title="bsuite",
    build_tasks=build_tasks,
    env_module="rlu.domains.bsuite.env",
    release_module="rlu.domains.bsuite.release",
    extra="bsuite",
    packages=("bsuite", "gymnasium"),
    datasets="noise_run",
    vector_backend="sync",
)
