"""The one registry of every RL Unplugged task: datasets and environments are built from it.

Sources for every number here:
- observation keys, dims and action dims: the ``shapes`` tables of the original
  ``rl_unplugged/dm_control_suite.py`` (github.com/deepmind/deepmind-research);
- selection split, episode counts, sequence lengths: the paper's tables 1-4 (Gulcehre et al.
  2020, arXiv:2006.13888);
- release paths and shard counts: the release bucket's layout, as the original loaders
  (``rl_unplugged/*.py``) name them;
- Atari minimal action-set sizes: read from ale-py 0.12.1 (``tests/test_tasks.py`` re-checks them
  against ALE when the ``atari`` extra is installed).

Names: every function that takes a task id (``get_task``, ``resolve_task`` and all that call
them) also takes a bare name when it is unambiguous (``walker_walk`` is not: control suite and
RWRL both have it) and TensorFlow Datasets' names for RL Unplugged (``TFDS_BUILDERS``):
``rlu_control_suite/cartpole_swingup``, ``rlu_locomotion/rodent_gaps``, ``rlu_atari/Pong_run_1``
(also ``rlu_atari_checkpoints_ordered/...``), ``rlu_rwrl/walker_walk_combined_challenge_easy_
100_percent``, with or without a ``:VERSION`` suffix. A TFDS name also picks the dataset TFDS
builds from: the release family it reads (``dm_control_suite_episodes``, the whole-episode
files, for ``rlu_control_suite``) and the Atari run or RWRL challenge and size
(``TaskRef.dataset_settings``).
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Literal

from rlu.types import (
    ActionSpec,
    ArraySpec,
    BoundedSpec,
    DiscreteSpec,
    ObservationSpec,
    RluError,
    observation_spec_to_json,
)

Domain = Literal["control_suite", "locomotion", "atari", "rwrl"]
DOMAINS: tuple[str, ...] = ("control_suite", "locomotion", "atari", "rwrl")
BUCKET = "rl_unplugged"
BASE_URL = "https://storage.googleapis.com/rl_unplugged"
# Gymnasium ids (TaskSpec.gym_id) and the entry point of their specs, a string so that a spec
# stored as JSON (Minari keeps one per dataset) makes the env again (rlu.envs.registration).
GYM_NAMESPACE = "rlu"
GYM_VERSION = 0
GYM_ENTRY_POINT = "rlu.envs.registration:make"


@dataclass(frozen=True)
class ReleaseDataset:
    """One family of files of the original release for a task.

    ``path`` is the object prefix inside the bucket, without the ``-%05d-of-%05d`` suffix, with
    ``{run}`` / ``{challenge}`` / ``{size}`` placeholders where the task has several datasets.
    ``shards`` maps a placeholder binding (e.g. ``"run_1"``, ``"none/large"``) or ``""`` to N.
    """

    family: str
    """The bucket's top folder: atari, atari_episodes_ordered, dm_control_suite, ..."""
    path: str
    shards: Mapping[str, int]
    seq_length: int | None = None
    """Steps per record for window files (2 or 40); None for whole-episode files."""

    def shard_names(self, binding: str = "") -> list[str]:
        n = self.shards[binding]
        prefix = self.path.format(**_binding_fields(binding))
        return [f"{prefix}-{i:05d}-of-{n:05d}" for i in range(n)]


def _binding_fields(binding: str) -> dict[str, str]:
    if not binding:
        return {}
    if binding.startswith("run_"):
        return {"run": binding}
    challenge, size = binding.split("/")
    # paper sizes small / medium / large are the bucket's 20 / 40 / 100 percent folders
    return {"challenge": challenge, "size": RWRL_SIZES.get(size, size)}


@dataclass(frozen=True)
class TaskSpec:
    """Everything rlu knows about one task; datasets and envs both read it."""

    id: str
    domain: Domain
    name: str
    observation_spec: ObservationSpec
    action_spec: ActionSpec
    episode_length: int
    """Maximum agent steps per episode (time limit)."""
    selection: Literal["online", "offline"]
    episodes: Mapping[str, int]
    """Paper episode counts per dataset ("" for one dataset; "none/small" etc. for RWRL)."""
    release: tuple[ReleaseDataset, ...]
    env: Mapping[str, Any] = field(default_factory=dict)
    """Entry-point parameters for ``rlu.envs`` (suite domain/task, game, builder name)."""
    seq_length: int = 1
    """Paper sequence length (locomotion 2 or 40; 1 = transitions)."""
    datasets: tuple[str, ...] = ("",)
    """Dataset variants: Atari runs ``run_1..run_5``, RWRL ``none/small`` ... ``easy/large``."""

    @property
    def discrete(self) -> bool:
        """Whether the task's actions are discrete (Atari)."""
        return isinstance(self.action_spec, DiscreteSpec)

    @property
    def gym_id(self) -> str:
        """The task's Gymnasium id, ``rlu/DOMAIN-NAME-v0`` (registered by ``rlu.envs``; the
        domain is kept because RWRL and the control suite share task names)."""
        return f"{GYM_NAMESPACE}/{self.domain}-{self.name}-v{GYM_VERSION}"

    def max_episode_steps(self, env_settings: Mapping[str, Any] | None = None) -> int:
        """Agent steps after which the env made with ``env_settings`` truncates an episode
        (Gymnasium's ``spec.max_episode_steps``): ``episode_length``, or Atari's
        ``max_episode_steps`` setting."""
        if self.domain == "atari" and env_settings and "max_episode_steps" in env_settings:
            return int(env_settings["max_episode_steps"])
        return self.episode_length

    @property
    def action_dim(self) -> int:
        """Discrete actions: how many; continuous: the action vector's size."""
        if isinstance(self.action_spec, DiscreteSpec):
            return self.action_spec.num_values
        return self.action_spec.size

    def release_dataset(self, family: str | None = None) -> ReleaseDataset:
        """The task's release dataset of ``family`` (None: its first, the default family); an
        unknown family raises an error listing the task's."""
        if family is None:
            return self.release[0]
        for r in self.release:
            if r.family == family:
                return r
        known = ", ".join(r.family for r in self.release)
        raise RluError(f"task {self.id!r} has no release family {family!r}; it has: {known}")

    def to_json(self) -> dict[str, Any]:
        """The task as JSON: what ``rlu info TASK --json`` and ``rlu list --json`` print."""
        return {
            "id": self.id,
            "domain": self.domain,
            "name": self.name,
            "selection": self.selection,
            "discrete": self.discrete,
            "action_dim": self.action_dim,
            "action_spec": self.action_spec.to_json(),
            "observation_spec": observation_spec_to_json(self.observation_spec),
            "episode_length": self.episode_length,
            "seq_length": self.seq_length,
            "episodes": dict(self.episodes),
            "datasets": list(self.datasets),
            "env": dict(self.env),
            "release": [
                {
                    "family": r.family,
                    "path": r.path,
                    "shards": dict(r.shards),
                    "seq_length": r.seq_length,
                }
                for r in self.release
            ],
        }


def _f32(*shape: int) -> ArraySpec:
    return ArraySpec(tuple(shape), "float32")


def _obs(**dims: int) -> Mapping[str, ArraySpec]:
    return MappingProxyType({k: _f32(d) for k, d in dims.items()})


def _act(n: int) -> BoundedSpec:
    return BoundedSpec((n,), "float32", -1.0, 1.0)


CAMERA = ArraySpec((64, 64, 3), "uint8")
ATARI_FRAME_STACK = 4
ATARI_OBSERVATION = ArraySpec((84, 84, ATARI_FRAME_STACK), "uint8")
# 108K frames at frame skip 4 (the paper's / Dopamine's convention); rlu.envs documents the
# original evaluation wrapper's 108,000-agent-step variant.
ATARI_MAX_AGENT_STEPS = 27_000

# --- DM Control Suite (paper table 1) -------------------------------------------------------
_CONTROL = {
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

# --- DM Locomotion (paper table 2) ----------------------------------------------------------
_HUMANOID_OBS = dict(
    joints_vel=56,
    sensors_velocimeter=3,
    sensors_gyro=3,
    joints_pos=56,
    world_zaxis=3,
    body_height=1,
    sensors_accelerometer=3,
    end_effectors_pos=12,
)
_RODENT_OBS = dict(
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
_LOCOMOTION = {
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

# --- Atari (paper table 3) ------------------------------------------------------------------
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

# --- RWRL (paper table 4; shard counts from TFDS rlu_rwrl SHARDS_MAPPING) --------------------
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


def _build() -> dict[str, TaskSpec]:
    tasks: dict[str, TaskSpec] = {}

    for name, (dims, adim, n_ep, sel) in _CONTROL.items():
        domain, task = name.split("_", 1)
        tasks[f"control_suite/{name}"] = TaskSpec(
            id=f"control_suite/{name}",
            domain="control_suite",
            name=name,
            observation_spec=_obs(**dims),
            action_spec=_act(adim),
            episode_length=1000,
            selection=sel,
            episodes=MappingProxyType({"": n_ep}),
            release=(
                ReleaseDataset("dm_control_suite", f"dm_control_suite/{name}/train", {"": 100}, 2),
                ReleaseDataset(
                    "dm_control_suite_episodes",
                    f"dm_control_suite_episodes/{name}/train",
                    {"": 100},
                ),
            ),
            env=MappingProxyType({"suite_domain": domain, "suite_task": task}),
        )

    for name, (walker, adim, n_ep, seq, sel, rdir, rseq, ep_len) in _LOCOMOTION.items():
        dims = _HUMANOID_OBS if walker == "humanoid" else _RODENT_OBS
        obs = {f"walker/{k}": _f32(d) for k, d in dims.items()}
        obs["walker/egocentric_camera"] = CAMERA
        tasks[f"locomotion/{name}"] = TaskSpec(
            id=f"locomotion/{name}",
            domain="locomotion",
            name=name,
            observation_spec=MappingProxyType(obs),
            action_spec=_act(adim),
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

    for game in ATARI_ONLINE + ATARI_OFFLINE:
        n_ordered = 49 if game in _ATARI_49_SHARDS else 50
        tasks[f"atari/{game}"] = TaskSpec(
            id=f"atari/{game}",
            domain="atari",
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

    for name, (sdom, stask, dims, adim, eps, shards_none, shards_easy) in _RWRL.items():
        episodes = {f"none/{s}": n for s, n in zip(RWRL_SIZES, eps, strict=True)}
        episodes["easy/large"] = eps[2]
        shards = {f"none/{s}": n for s, n in zip(RWRL_SIZES, shards_none, strict=True)}
        shards["easy/large"] = shards_easy
        tasks[f"rwrl/{name}"] = TaskSpec(
            id=f"rwrl/{name}",
            domain="rwrl",
            name=name,
            # Challenge `easy` adds the scalar keys dummy-0..dummy-9 (rlu.envs / release reader).
            observation_spec=_obs(**dims),
            action_spec=_act(adim),
            episode_length=1000,
            selection="online",
            episodes=MappingProxyType(episodes),
            release=(
                ReleaseDataset(
                    "rwrl",
                    f"rwrl/combined_challenge_{{challenge}}/{sdom}/{stask}/{{size}}/episodes.tfrecord",
                    MappingProxyType(shards),
                ),
            ),
            env=MappingProxyType({"suite_domain": sdom, "suite_task": stask}),
            datasets=RWRL_DATASETS,
        )
    return tasks


TASKS: Mapping[str, TaskSpec] = MappingProxyType(_build())


def rwrl_observation_spec(task: TaskSpec, challenge: str) -> Mapping[str, ArraySpec]:
    """Observation spec of an RWRL task under a challenge (``easy`` adds 10 dummy scalars)."""
    spec = dict(task.observation_spec)  # type: ignore[arg-type]
    if challenge == "easy":
        spec.update({k: _f32(1) for k in RWRL_EASY_DUMMY_KEYS})
    elif challenge != "none":
        raise RluError(f"RWRL challenge {challenge!r} is not released; use 'none' or 'easy'")
    return MappingProxyType(spec)


# --- names: ids, bare names and TensorFlow Datasets' names --------------------------------------
# TFDS builder -> (rlu domain, the release family the builder reads). Sources: tensorflow_datasets
# rl_unplugged/<builder>/<builder>.py ``_INPUT_FILE_PREFIX`` and ``BUILDER_CONFIGS`` (config names
# ``<task>``, ``<Game>_run_<N>``, ``<domain>_<task>_combined_challenge_<none|easy>_<P>_percent``).
TFDS_BUILDERS: Mapping[str, tuple[str, str]] = MappingProxyType(
    {
        "rlu_control_suite": ("control_suite", "dm_control_suite_episodes"),
        "rlu_locomotion": ("locomotion", "dm_locomotion_episodes"),
        "rlu_atari": ("atari", "atari_episodes_ordered"),
        "rlu_atari_checkpoints_ordered": ("atari", "atari_episodes_ordered"),
        "rlu_rwrl": ("rwrl", "rwrl"),
    }
)
_TFDS_VERSION = re.compile(r":\d+(\.\d+)*$")
_TFDS_ATARI = re.compile(r"^(?P<game>[A-Za-z]+)_run_(?P<run>\d+)$")
_TFDS_RWRL = re.compile(
    r"^(?P<task>[a-z]+_[a-z]+)_combined_challenge_(?P<challenge>none|easy)_(?P<size>\d+_percent)$"
)


@dataclass(frozen=True)
class TaskRef:
    """A task as a name picked it, with the dataset settings the name carries (TFDS names do)."""

    task: TaskSpec
    name: str
    """The name as given (``control_suite/cartpole_swingup``, ``rlu_atari/Pong_run_1``)."""
    family: str | None = None
    """The release family the name reads (TFDS names), None: the task's default."""
    run: str | None = None
    """Atari run ``run_N`` the name picks."""
    challenge: str | None = None
    """RWRL challenge (``none`` / ``easy``) the name picks."""
    size: str | None = None
    """RWRL dataset size in the paper's words (``small`` / ``medium`` / ``large``)."""

    def dataset_settings(
        self,
        family: str | None = None,
        run: str | int | None = None,
        challenge: str | None = None,
        size: str | None = None,
    ) -> tuple[str | None, str | int | None, str | None, str | None]:
        """(family, run, challenge, size): what was passed, filled in from the name; a value
        that contradicts the name is an error naming both."""
        given = {"family": family, "run": run, "challenge": challenge, "size": size}
        named = {"family": self.family, "run": self.run, "challenge": self.challenge}
        named["size"] = self.size
        out = {}
        for key, value in given.items():
            mine = named[key]
            if value is not None and mine is not None and _norm(key, value) != mine:
                raise RluError(
                    f"{self.name} names {key} {mine!r}, which contradicts {key}={value!r}; drop "
                    f"the {key} or use the task id {self.task.id}"
                )
            out[key] = value if value is not None else mine
        return out["family"], out["run"], out["challenge"], out["size"]


def _norm(key: str, value: str | int) -> str:
    if key == "run":
        return str(value) if str(value).startswith("run_") else f"run_{value}"
    if key == "size":
        return {v: k for k, v in RWRL_SIZES.items()}.get(str(value), str(value))
    return str(value)


def resolve_task(name: str) -> TaskRef:
    """The task ``name`` names (an id, an unambiguous bare name or a TFDS name), with the dataset
    settings a TFDS name carries; an unknown name raises an error listing the closest ids."""
    if name in TASKS:
        return TaskRef(TASKS[name], name)
    builder = name.split("/", 1)[0]
    if builder in TFDS_BUILDERS or builder.startswith("rlu_"):
        return _resolve_tfds(name)
    # Accept a bare name when it is unambiguous ("cartpole_swingup" -> control_suite/...).
    bare = [t for t in TASKS.values() if t.name.lower() == name.lower()]
    if len(bare) == 1:
        return TaskRef(bare[0], name)
    needle = name.split("/")[-1].lower()
    close = [t.id for t in TASKS.values() if needle and needle in t.id.lower()][:5]
    if not close:
        close = difflib.get_close_matches(name, list(TASKS), n=5, cutoff=0.6)
    if not close:
        close = difflib.get_close_matches(
            name.split("/")[-1], [t.name for t in TASKS.values()], n=5, cutoff=0.4
        )
        close = [t.id for t in TASKS.values() if t.name in close]
    hint = f" Closest: {', '.join(close)}." if close else ""
    raise RluError(f"unknown task id {name!r}.{hint} `rlu list` prints every id.")


_TFDS_EXAMPLES = {
    "rlu_control_suite": "rlu_control_suite/cartpole_swingup",
    "rlu_locomotion": "rlu_locomotion/rodent_gaps",
    "rlu_atari": "rlu_atari/Pong_run_1",
    "rlu_atari_checkpoints_ordered": "rlu_atari_checkpoints_ordered/Pong_run_1",
    "rlu_rwrl": "rlu_rwrl/walker_walk_combined_challenge_none_100_percent",
}


def _resolve_tfds(name: str) -> TaskRef:
    builder, _, config = _TFDS_VERSION.sub("", name).partition("/")
    if builder not in TFDS_BUILDERS:
        if builder == "rlu_atari_checkpoints":
            why = (
                "it reads the atari_episodes_v2 files, which rlu does not read; rlu reads the "
                "files of rlu_atari and rlu_atari_checkpoints_ordered (atari_episodes_ordered), "
                "e.g. rlu_atari/Pong_run_1"
            )
        elif builder.startswith("rlu_dmlab"):
            why = "DMLab is not a registered task; rlu convert --family dmlab reads its files"
        else:
            why = f"rlu knows the TFDS builders {', '.join(TFDS_BUILDERS)}"
        raise RluError(f"{name!r}: TFDS builder {builder!r} has no rlu task: {why}")
    domain, family = TFDS_BUILDERS[builder]
    fix = f"TFDS names read like {_TFDS_EXAMPLES[builder]} (`rlu list --domain {domain}`)"
    if not config:
        raise RluError(f"{name!r} names no config; {fix}")
    if domain in ("control_suite", "locomotion"):
        task = TASKS.get(f"{domain}/{config}")
        if task is None:
            raise RluError(f"{name!r}: {builder} has no config {config!r}; {fix}")
        return TaskRef(task, name, family=family)
    if domain == "atari":
        m = _TFDS_ATARI.match(config)
        games = {t.name.lower(): t for t in TASKS.values() if t.domain == "atari"}
        task = games.get(m["game"].lower()) if m else None
        run = f"run_{m['run']}" if m else ""
        if task is None or run not in task.datasets:
            raise RluError(f"{name!r}: {builder} has no config {config!r}; {fix}")
        return TaskRef(task, name, family=family, run=run)
    m = _TFDS_RWRL.match(config)
    task = TASKS.get(f"rwrl/{m['task']}") if m else None
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


def get_task(task_id: str) -> TaskSpec:
    """The TaskSpec of ``task_id`` (an id, a bare name or a TFDS name: ``resolve_task``)."""
    return resolve_task(task_id).task


def list_tasks(domain: str | None = None, selection: str | None = None) -> list[TaskSpec]:
    """Every TaskSpec, optionally filtered by domain and selection split."""
    if domain is not None and domain not in DOMAINS:
        raise RluError(f"unknown domain {domain!r}; use one of {', '.join(DOMAINS)}")
    return [
        t
        for t in TASKS.values()
        if (domain is None or t.domain == domain)
        and (selection is None or t.selection == selection)
    ]


def check_challenge(task: str, challenge: str, keys: set[str], recorded: str, what: str) -> None:
    """An RWRL policy runs only where the env gives the observation keys its data had (the easy
    challenge adds dummy observations): refuse a challenge whose keys differ."""
    wanted = set(rwrl_observation_spec(get_task(task), challenge))
    if wanted != keys:
        differ = sorted(wanted ^ keys)
        raise RluError(
            f"{what} was recorded under RWRL challenge {recorded!r}; challenge {challenge!r} gives "
            f"other observations ({', '.join(differ[:4])}{' ...' if len(differ) > 4 else ''}), so "
            f"its policies cannot run there: evaluate under {recorded!r} (drop --challenge)"
        )


def _spec_text(spec: ObservationSpec | ActionSpec) -> str:
    if isinstance(spec, Mapping):
        return "{" + ", ".join(f"{k}: {tuple(v.shape)}" for k, v in sorted(spec.items())) + "}"
    if isinstance(spec, DiscreteSpec):
        return f"{spec.num_values} discrete actions"
    return str(tuple(spec.shape))


def check_data_matches(
    task_id: str,
    observation_spec: ObservationSpec,
    action_spec: ActionSpec,
    what: str,
    recorded_task: str | None = None,
    challenge: str = "none",
) -> None:
    """Refuse, before any training step, a dataset whose observations or actions are not those
    of ``task_id``'s env (``what`` names the dataset; ``recorded_task``: the task its manifest
    names). Observations are compared as the agent sees them (Atari: stacked frames)."""
    task = get_task(task_id)
    fix = f"train --task {recorded_task} on it" if recorded_task else "pass the dataset's own task"
    if recorded_task and recorded_task in TASKS and TASKS[recorded_task].id != task.id:
        raise RluError(
            f"{what} holds data of task {recorded_task}, not {task.id}: {fix}, or give a "
            f"dataset of {task.id}"
        )
    want_obs = (
        rwrl_observation_spec(task, challenge) if task.domain == "rwrl" else task.observation_spec
    )

    def shapes(spec: ObservationSpec) -> Any:
        if isinstance(spec, Mapping):
            return {k: tuple(v.shape) for k, v in spec.items()}
        return tuple(spec.shape)

    if shapes(observation_spec) != shapes(want_obs):
        raise RluError(
            f"{what}: its observations {_spec_text(observation_spec)} are not those of "
            f"{task.id}'s env {_spec_text(want_obs)}; {fix}, or give a dataset of {task.id}"
        )
    want_act = task.action_spec
    same = type(action_spec) is type(want_act) and tuple(action_spec.shape) == tuple(want_act.shape)
    if same and isinstance(want_act, DiscreteSpec):
        same = action_spec.num_values == want_act.num_values  # type: ignore[union-attr]
    if not same:
        raise RluError(
            f"{what}: its actions ({_spec_text(action_spec)}) are not those of {task.id}'s env "
            f"({_spec_text(want_act)}); {fix}, or give a dataset of {task.id}"
        )
