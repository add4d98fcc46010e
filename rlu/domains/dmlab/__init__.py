"""DeepMind Lab (the release's ``dmlab/`` files): five levels recorded by R2D2 agents.

Release facts (the original ``rl_unplugged/dmlab_r2d2.ipynb``; TensorFlow Datasets'
``rl_unplugged/dmlab_dataset.py``, the ``rlu_dmlab_*`` builders and
``rlu_dmlab_seekavoid_arena01/checksums.tsv``): objects ``dmlab/<level>/<run>/tfrecord-%05d-of-
00500`` (500 GZIP TFRecord shards a run), runs ``training_0`` to ``training_2`` for every level
(R2D2's whole training runs, every actor's experience) and, for seekavoid_arena_01 only,
``snapshot_{0,1}_eps_{0.0,0.01,0.1,0.25}`` (a trained snapshot run epsilon-greedy; the notebook's
table lists the four epsilons, TFDS's config list leaves out 0.1). One record is one episode of
a fixed T steps (seekavoid_arena_01 301, explore_object_rewards_few 1351,
explore_object_rewards_many 1801, rooms_select_nonmatching_object 181, rooms_watermaze 1801):
``observations_pixels`` (T PNG frames 72x96x3, stored BGR: OpenCV wrote them),
``observations_action`` (the previous action one-hot, T x 15), ``observations_reward`` (the
previous reward), ``actions`` (int64, 15 discrete actions), ``rewards``, ``discounts``,
``discounted_rewards``, and the scalars ``episode_id``, ``start_idx``, ``episode_return``.

Observations here are the dict TFDS names (``pixels`` RGB, the reader reverses the stored BGR;
``last_action`` kept one-hot as stored, TFDS gives its argmax; ``last_reward``). A task's
``episode_length`` is T - 1 agent steps: the first record step is the start observation. The
TFDS builder names drop a level's underscore before ``01`` (``rlu_dmlab_seekavoid_arena01``);
the release README spells two levels ``explore_rewards_*``, the objects
``explore_object_rewards_*``.
The dataset is described in Gulcehre et al. 2021 ("Regularized Behavior Value Estimation"); the
paper rlu follows for the other domains (Gulcehre et al. 2020) reports no DMLab numbers.

DeepMind Lab is not on PyPI: its env (``rlu.domains.dmlab.env``) needs the ``deepmind_lab``
module built from source (:data:`ENV_INSTALL`).
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING

from rlu.domains import Domain
from rlu.domains.common import f32
from rlu.types import ArraySpec

if TYPE_CHECKING:  # pragma: no cover
    from rlu.domains.spec import TaskRef, TaskSpec

NAME = "dmlab"
SHARDS = 500
"""Shards of every run (``tfrecord-%05d-of-00500``)."""
NUM_ACTIONS = 15
FRAME = (72, 96, 3)
TRAINING_RUNS = tuple(f"training_{k}" for k in range(3))
SNAPSHOT_RUNS = tuple(
    f"snapshot_{k}_eps_{eps}" for eps in ("0.0", "0.01", "0.1", "0.25") for k in range(2)
)
LEVELS = {
    # level (the release's folder): (steps per record T, runs, TFDS builder)
    "seekavoid_arena_01": (301, TRAINING_RUNS + SNAPSHOT_RUNS, "rlu_dmlab_seekavoid_arena01"),
    "explore_object_rewards_few": (1351, TRAINING_RUNS, "rlu_dmlab_explore_object_rewards_few"),
    "explore_object_rewards_many": (1801, TRAINING_RUNS, "rlu_dmlab_explore_object_rewards_many"),
    "rooms_select_nonmatching_object": (
        181,
        TRAINING_RUNS,
        "rlu_dmlab_rooms_select_nonmatching_object",
    ),
    "rooms_watermaze": (1801, TRAINING_RUNS, "rlu_dmlab_rooms_watermaze"),
}
ENV_INSTALL = (
    "DeepMind Lab is not on PyPI: build its Python module from source "
    "(https://github.com/google-deepmind/lab: install Bazel, then in the checkout "
    "`bazel build -c opt --python_version=PY3 //python/pip_package:build_pip_package`, "
    "`./bazel-bin/python/pip_package/build_pip_package /tmp/dmlab_pkg` and "
    "`pip install /tmp/dmlab_pkg/deepmind_lab-*.whl`; its python/pip_package/README.md and "
    "docs/users/build.md have the details), "
    "so that `import deepmind_lab` works"
)
"""How the env's ``deepmind_lab`` module is installed (no pip extra can)."""
DATA_ONLY = (
    "DeepMind Lab is data only here: deepmind_lab is not on PyPI, and the release documents "
    "neither the recording R2D2 agent's 15 actions (the DeepMind Lab action vector of each "
    "index) nor its action repeat"
)
"""Why rlu makes no DeepMind Lab env (``rlu list`` prints it; ``rlu.domains.dmlab.env`` refuses)."""


def observation_spec() -> Mapping[str, ArraySpec]:
    """The dict observation of every level: ``pixels`` RGB, ``last_action`` one-hot,
    ``last_reward``."""
    return MappingProxyType(
        {
            "pixels": ArraySpec(FRAME, "uint8"),
            "last_action": f32(NUM_ACTIONS),
            "last_reward": f32(),
        }
    )


def build_tasks() -> list[TaskSpec]:
    """The DMLab TaskSpecs."""
    from rlu.domains.spec import ReleaseDataset, TaskSpec
    from rlu.types import DiscreteSpec

    tasks = []
    for level, (steps, runs, builder) in LEVELS.items():
        tasks.append(
            TaskSpec(
                id=f"{NAME}/{level}",
                domain=NAME,
                name=level,
                observation_spec=observation_spec(),
                action_spec=DiscreteSpec((), "int64", NUM_ACTIONS),
                episode_length=steps - 1,
                selection="offline",  # no paper table holds DMLab
                episodes=MappingProxyType({}),
                release=(
                    ReleaseDataset(
                        "dmlab", f"dmlab/{level}/{{run}}/tfrecord", {r: SHARDS for r in runs}
                    ),
                ),
                env=MappingProxyType({"level": level, "tfds_builder": builder}),
                datasets=runs,
            )
        )
    return tasks


_BUILDERS = {builder: level for level, (_, _, builder) in LEVELS.items()}


def tfds_ref(
    tasks: Mapping[str, TaskSpec], name: str, builder: str, config: str, family: str, fix: str
) -> TaskRef:
    """``rlu_dmlab_<level>/<run>`` (``rlu_dmlab_seekavoid_arena01/training_0``): the level's task
    and run."""
    from rlu.domains.spec import TaskRef
    from rlu.types import RluError

    task = tasks[f"{NAME}/{_BUILDERS[builder]}"]
    if config not in task.datasets:
        raise RluError(
            f"{name!r}: {builder} has no config {config!r}; {fix} (runs: "
            f"{', '.join(task.datasets)})"
        )
    return TaskRef(task, name, family=family, run=config)


DOMAIN = Domain(
    name=NAME,
    title="DeepMind Lab",
    build_tasks=build_tasks,
    env_module="rlu.domains.dmlab.env",
    release_module="rlu.domains.dmlab.release",
    extra="dmlab",
    packages=("deepmind_lab", "gymnasium"),
    env_install=ENV_INSTALL,
    data_only=DATA_ONLY,
    datasets="run_names",
    vector_backend="sync",
    tfds_builders=MappingProxyType({b: "dmlab" for b in _BUILDERS}),
    tfds_examples=MappingProxyType({b: f"{b}/training_0" for b in _BUILDERS}),
    tfds_ref=tfds_ref,
)
