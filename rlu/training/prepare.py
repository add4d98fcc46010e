"""A run before its first step: what it trains (:class:`TrainConfig`, checked as it is built),
then every check and every resolution of that config, giving one :class:`Prepared` value that
the loop (``rlu.training.loop``) reads and never changes.

What is resolved here: the datasets (``rlu.load_dataset``, once each), the output folder
against them (``rlu.files.check_output``), the specs the agent sees, the agent's config from its
preset and overrides, the evaluation env's settings, the data against the task, and the run's
resolved config (config.json). A run folder that already holds a run is checked against it:
``resume`` must be asked for and the configuration must be the same (``comparable``); a
finished run comes back as its result. Nothing is written here.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rlu.devices import Runtime
from rlu.files import Checked, bounds, check_output, shape_of
from rlu.training import runs
from rlu.training.config import RunSettings
from rlu.types import (
    ArraySpec,
    ConfigError,
    DiscreteSpec,
    ObservationSpec,
    RluError,
    observation_spec_to_json,
)


@dataclass(frozen=True)
class TrainConfig(Checked):
    """What one run trains, and how (``run``)."""

    task: str
    """Task id (the env to evaluate in), e.g. control_suite/cartpole_swingup."""
    agent: str
    """Agent name (bc, d4pg, ...; `rlu agents` lists them) or a module path following the
    agent-module convention (imported because you typed it; docs/agents.md)."""
    dataset: str | tuple[str, ...]
    """The data, as rlu.load_dataset names it: a task id (the dataset rlu ships, or the release's
    converted in the cache), a TFDS name (rlu_control_suite/cartpole_swingup) or a dataset
    folder (rlu convert / rlu generate / rlu import output); or several of one schema: a
    mixture, streamed (the first is the evaluation task's)."""
    seed: int = field(default=0, metadata=bounds(min=0, max=2**63 - 1))
    """Seeds the agent, the sampler and the evaluation episodes."""
    overrides: Mapping[str, Any] = field(default_factory=dict)
    """Agent config fields to change from the preset."""
    run: RunSettings = field(default_factory=RunSettings)
    """How the run is run: preset, budget, evaluation, checkpoints, runtime."""
    weights: tuple[float, ...] | None = field(
        default=None, metadata=bounds(gt=0.0, max=1e12, metavar="W")
    )
    """Share of each dataset's samples in a mixture (default: by their sizes)."""

    def __post_init__(self) -> None:
        super().__post_init__()  # every field's type and bounds (rlu.files.Checked)
        paths = (self.dataset,) if isinstance(self.dataset, str | os.PathLike) else self.dataset
        if (
            not isinstance(paths, tuple | list)
            or not paths
            or not all(isinstance(p, str | os.PathLike) for p in paths)
        ):
            raise RluError(f"dataset {self.dataset!r}; give a dataset path, or several")
        paths = tuple(os.fspath(p) for p in paths)
        object.__setattr__(self, "dataset", paths[0] if len(paths) == 1 else paths)
        if self.weights is not None:
            w = tuple(self.weights)
            if len(w) != len(paths) or not all(
                isinstance(x, int | float) and not isinstance(x, bool) and 0 < x < float("inf")
                for x in w
            ):
                raise RluError(
                    f"weights {list(w)}; give one positive number per dataset ({len(paths)})"
                )
            object.__setattr__(self, "weights", w)

    def datasets(self) -> tuple[str, ...]:
        """The dataset paths (one, or a mixture's)."""
        return (self.dataset,) if isinstance(self.dataset, str) else tuple(self.dataset)

    def to_json(self) -> dict[str, Any]:
        """The config as a run's config.json holds it (``train``)."""
        d = dataclasses.asdict(self)
        d["overrides"] = dict(self.overrides)
        return d

    @staticmethod
    def shape() -> Any:
        """The shape of ``to_json()`` in a run's config.json (``rlu.files``)."""
        return shape_of(TrainConfig)

    @classmethod
    def from_file(cls, path: str | os.PathLike, **fields: Any) -> TrainConfig:
        """The run config of a file, as ``rlu train --config FILE`` reads it: JSON or YAML with
        TrainConfig's fields (``run:`` holding RunSettings'), or a run folder's config.json.
        ``fields`` fill or replace top-level fields (``TrainConfig.from_file("bc.yaml",
        seed=1)``); a module path in the file (a dotted agent, ``run.env``) is refused unless
        ``fields`` names that field (names in files are never imported). The file's overrides
        are checked against the agent's config here (:func:`check_agent_config`)."""
        from rlu.training.config import config_from_file

        config = config_from_file(cls, os.fspath(path), fields)
        if "overrides" not in fields:  # the file's: a bad one names the file and its key
            origins = {key: f"{os.fspath(path)}: overrides.{key}" for key in config.overrides}
            check_agent_config(config, origins)
        return config


# --- agents ---------------------------------------------------------------------------------
def agent_config(name: str, discrete: bool, preset: str, overrides: Mapping[str, Any]) -> Any:
    from rlu.agents import make_config

    return make_config(name, discrete, preset, **overrides)


def check_agent_config(config: TrainConfig, origins: Mapping[str, str] | None = None) -> None:
    """Build ``config``'s agent config (its preset with the overrides) once, before a dataset
    is opened or a folder made, so that a bad override fails first; ``origins`` says where each
    override came from (``{"gamma": "bc.yaml: overrides.gamma"}``), and its error says so. The
    action kind comes from the task registry (without an env factory of its own, the data must
    match the task), or from the agent when it has one kind only; otherwise the config is
    checked once the data says which (``rlu.training.prepare``)."""
    from rlu.agents import AGENTS, make_config, trusted_agents
    from rlu.tasks import TASKS

    if "." in config.agent and config.agent not in trusted_agents():
        return  # checked once train() has imported it (trust)
    spec = TASKS.get(config.task) if config.run.env is None else None  # else the data decides
    if spec is not None:
        discrete = spec.discrete
    else:
        kinds = {d for n, d in AGENTS if n == config.agent}
        if "." in config.agent:
            kinds = {False}  # a trusted module serves both kinds
        if len(kinds) != 1:
            return
        (discrete,) = kinds
    preset = config.run.preset
    for key, value in config.overrides.items():
        try:
            make_config(config.agent, discrete, preset, **{key: value})
        except ConfigError as e:
            where = (origins or {}).get(key)
            raise (ConfigError(f"{where}: {e}") if where else e) from None
    make_config(config.agent, discrete, preset, **config.overrides)


def comparable(resolved: Mapping[str, Any]) -> dict[str, Any]:
    """A run's resolved config without its runtime: what must match for ``--resume``."""
    out = json.loads(json.dumps(resolved))
    train = out.get("train", {})
    train.get("run", {}).pop("runtime", None)
    # a field left at its default compares equal to its absence: a run begun before the field
    # existed resumes
    for holder, cls in ((train, TrainConfig), (train.get("run", {}), RunSettings)):
        for f in dataclasses.fields(cls):
            if f.default is not dataclasses.MISSING and holder.get(f.name, ...) == f.default:
                holder.pop(f.name)
    return out


# --- a prepared run ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Prepared:
    """A checked, resolved run: what the loop builds from and records."""

    config: TrainConfig
    run: Path
    """The run folder (not written yet)."""
    runtime: Runtime
    """``config.run.runtime`` resolved (its device chosen)."""
    opened: tuple[Any, ...]
    """The datasets, opened; the first is the evaluation task's."""
    obs_spec: ObservationSpec
    action_spec: ArraySpec | DiscreteSpec
    agent_cfg: Any
    """The agent's typed config: its preset with the overrides."""
    env_kwargs: Mapping[str, Any]
    """Keyword settings of the evaluation env (an RWRL challenge)."""
    resolved: Mapping[str, Any]
    """What config.json records."""
    checkpoints: tuple[Path, ...]
    """The run folder's checkpoints, oldest first (resume continues from the last)."""
    finished: dict[str, Any] | None
    """result.json of a run that had finished (resumed: nothing to do), else None."""

    @property
    def settings(self) -> RunSettings:
        return self.config.run

    @property
    def dataset(self) -> Any:
        """The evaluation task's dataset (a mixture's others share its schema)."""
        return self.opened[0]

    @property
    def discrete(self) -> bool:
        return isinstance(self.action_spec, DiscreteSpec)


def prepare(config: TrainConfig, run: Path, resume: bool) -> Prepared:
    """Check and resolve ``config`` for a run into folder ``run`` (see the module's doc)."""
    from rlu.data import load_dataset

    settings = config.run
    runtime = settings.runtime.resolve()
    # a task id, a TFDS name or a folder: the one resolver, once per dataset
    opened = tuple(load_dataset(name) for name in config.datasets())
    ds = opened[0]
    check_output(run, [d.path for d in opened], runs.CONFIG, "run folder")
    obs_spec, action_spec = dataset_specs(ds)
    discrete = isinstance(action_spec, DiscreteSpec)
    agent_cfg = agent_config(config.agent, discrete, settings.preset, config.overrides)
    env_kwargs = env_settings(config.task, ds, settings.challenge)
    if settings.env is None:
        from rlu.tasks import check_data_matches

        # an unknown task, or data of another task, fails here: before the run folder is touched
        check_data_matches(
            config.task,
            obs_spec,
            action_spec,
            f"dataset {ds.path}",
            ds.schema.task_id,
            env_kwargs.get("challenge", "none"),
        )
    resolved = _resolved(config, runtime, opened, obs_spec, action_spec, agent_cfg, env_kwargs)
    return Prepared(
        config=config,
        run=run,
        runtime=runtime,
        opened=opened,
        obs_spec=obs_spec,
        action_spec=action_spec,
        agent_cfg=agent_cfg,
        env_kwargs=env_kwargs,
        resolved=resolved,
        checkpoints=tuple(runs.checkpoints(run)) if resume else (),
        finished=_held_run(run, resume, resolved),
    )


def _resolved(
    config: TrainConfig,
    runtime: Runtime,
    opened: tuple[Any, ...],
    obs_spec: ObservationSpec,
    action_spec: ArraySpec | DiscreteSpec,
    agent_cfg: Any,
    env_kwargs: Mapping[str, Any],
) -> dict[str, Any]:
    """The content of a run's config.json."""
    ds = opened[0]
    resolved: dict[str, Any] = {
        "train": dataclasses.replace(
            config, run=dataclasses.replace(config.run, runtime=runtime)
        ).to_json(),
        "env_settings": dict(env_kwargs),
        "agent_config": _jsonable(agent_cfg),
        "observation_spec": observation_spec_to_json(obs_spec),
        "action_spec": action_spec.to_json(),
        "dataset": {"path": str(Path(ds.path).resolve()), "num_steps": int(ds.num_steps)},
    }
    if len(opened) > 1:  # the first one's path and steps above, every one's here
        resolved["dataset"]["mixture"] = {
            "paths": [str(Path(d.path).resolve()) for d in opened],
            "num_steps": [int(d.num_steps) for d in opened],
        }
    return resolved


def _held_run(run: Path, resume: bool, resolved: Mapping[str, Any]) -> dict[str, Any] | None:
    """Check a run folder that already holds a run against this one; its result if finished."""
    if not (run.exists() and (run / runs.CONFIG).exists()):
        return None
    if not resume:
        raise RluError(
            f"{run} already holds a run; pass --resume to continue it or choose a new --out"
        )
    old = runs.read_config(run, TrainConfig.shape())
    if comparable(old) != comparable(resolved):
        raise RluError(
            f"{run}/{runs.CONFIG} was written by a different configuration; resume with the "
            "same arguments or choose a new --out"
        )
    if (run / runs.RESULT).exists():
        return runs.read_result(run)
    return None


def dataset_specs(ds: Any) -> tuple[Any, Any]:
    """(observation spec as the agent sees it, action spec) from a dataset's schema."""
    schema = ds.schema
    obs = schema.observation
    if schema.frame_stack > 1:
        obs = ArraySpec((*obs.shape, schema.frame_stack), obs.dtype)
    return obs, schema.action


def env_settings(task: str, ds: Any, challenge: str | None = None) -> dict[str, Any]:
    """Keyword settings of the evaluation env: the data's RWRL challenge (or ``challenge``)."""
    from rlu.domains import DOMAINS
    from rlu.tasks import TASKS, check_challenge

    spec = TASKS.get(task)
    if spec is None or not DOMAINS[spec.domain].challenges:
        if challenge not in (None, "none"):
            raise RluError(f"--challenge applies to rwrl tasks only; {task} has none")
        return {}
    recorded = ds.manifest["provenance"].get("challenge") or "none"
    chosen = challenge or recorded
    check_challenge(task, chosen, set(dataset_specs(ds)[0]), recorded, str(ds.path))
    return {"challenge": chosen}


def _jsonable(x: Any) -> Any:
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: _jsonable(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x


def trust(agent: str, env: str | None) -> None:
    """Import and register what a config built by code or the command line names by module
    path: a dotted agent, an env factory. Runs read back from files never come here."""
    if "." in agent:
        from rlu.agents import trust_agent

        trust_agent(agent)
    if env is not None:
        from rlu.evaluation.rollout import trust_env_factory

        trust_env_factory(env)
