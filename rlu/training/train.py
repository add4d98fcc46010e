"""The one training loop: batch -> agent.update -> periodic evaluation in the env -> logs.
Three steps: ``rlu.training.prepare`` checks and resolves a ``TrainConfig`` (nothing written),
``rlu.training.loop`` builds the agent and runs the loop; this module holds the config and the
entry point, ``train``.

The agent declares its batches (``agent.batch_spec``) and the loop samples exactly those
(``rlu.data.make_sampler``); the run folder's layout and files belong to ``rlu.training.runs``; how
a run is run (preset, budget, evaluation, checkpoints, runtime) is one
``rlu.training.config.RunSettings``.

Resume is exact on the CPU: a checkpoint holds the agent's state, the sampler's generator, the
global torch and numpy generators and the step; on ``resume`` the logs are cut back to the
checkpoint's step and the loop goes on. Evaluation at step k uses env seeds derived from
(seed, k) only, so it needs no state.

Devices (``RunSettings.runtime``, docs/devices.md): the agent lives on the runtime's device;
batches come from the sampler in line (the CPU default), from a background prefetcher (CUDA's
default: pinned host batches copied on a side stream) or from the dataset held on the device;
every update runs in the runtime's precision. All three data paths give the same batches. The
runtime may differ between a run's sessions (train on a GPU, resume on a CPU): resume compares
the run's config without it, and checkpoints load on any device.

Agents are built by name through ``rlu.agents``; a dotted module path in a ``TrainConfig``
(``tests.train.fake_agent``: code or the command line named it) is imported and registered
(``rlu.agents.trust_agent``). Envs come from ``rlu.envs.make_env`` or from an env factory
``'module:function'`` given the same way. Names inside files are never imported.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rlu.files import Checked, bounds, shape_of
from rlu.training.config import RunSettings
from rlu.types import ArraySpec, ConfigError, RluError


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


YAML_BOOLEANS = {
    **dict.fromkeys(("true", "True", "TRUE", "yes", "Yes", "YES", "on", "On", "ON"), True),
    **dict.fromkeys(("false", "False", "FALSE", "no", "No", "NO", "off", "Off", "OFF"), False),
}
"""The words a YAML config file's reader (PyYAML's safe loader, YAML 1.1) reads as booleans; an
override on the command line reads them the same way (``recurrent=true``)."""


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """``["learning_rate=3e-4", "hidden=(256, 256)", "atari.batch_size=64", "recurrent=true"]``
    -> typed values: Python literals, YAML's booleans (:data:`YAML_BOOLEANS`, as a config file
    reads them); other bare words stay strings. The agent config checks each against its field
    (``recurrent=maybe`` or ``recurrent=1``: refused, "expected true or false")."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise RluError(f"override {item!r}; write it as field=value, e.g. learning_rate=3e-4")
        text = text.strip()
        if text in YAML_BOOLEANS:
            out[key.strip()] = YAML_BOOLEANS[text]
            continue
        try:
            out[key.strip()] = ast.literal_eval(text)
        except (ValueError, SyntaxError, MemoryError, RecursionError):
            out[key.strip()] = text
    return out


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


def trust(agent: str, env: str | None) -> None:
    """Import and register what a config built by code or the command line names by module
    path: a dotted agent, an env factory. Runs read back from files never come here."""
    if "." in agent:
        from rlu.agents import trust_agent

        trust_agent(agent)
    if env is not None:
        from rlu.evaluation.rollout import trust_env_factory

        trust_env_factory(env)


# --- the loop -------------------------------------------------------------------------------
def train(
    config: TrainConfig,
    out: str | os.PathLike,
    resume: bool = False,
    progress: bool | Any = False,
    loggers: Sequence[str] = (),
) -> dict[str, Any]:
    """Train ``config.agent`` on ``config.dataset``; returns the content of ``result.json``.
    ``loggers``: where the metrics go besides the run's own logs (``rlu.training.loggers.LOGGERS``).
    ``progress``: True shows the steps on stderr (``rlu.progress.Progress``); a
    ``rlu.progress.Relay`` sends them to the process that started this one (a sweep's run).

    One process per run folder: a second ``train`` into the same ``out`` fails with "in use by
    PID N" (:class:`rlu.locks.OutputLock`) while the first lives.
    """
    from rlu.locks import OutputLock

    trust(config.agent, config.run.env)
    check_agent_config(config)  # before the lock file, its folder, the data
    with OutputLock(Path(out), "run folder"):
        return _train(config, out, resume, progress, tuple(loggers))


def _train(
    config: TrainConfig,
    out: str | os.PathLike,
    resume: bool,
    progress: bool | Any,
    logger_names: tuple[str, ...],
) -> dict[str, Any]:
    from rlu.training.loop import build, result_of, run_loop, start_folder
    from rlu.training.prepare import prepare

    prepared = prepare(config, Path(out), resume)
    if prepared.finished is not None:  # a finished run resumed: nothing left to do
        return prepared.finished
    built = build(prepared, logger_names)
    # everything that can fail before the first step has run: only now is the run folder written
    loggers = start_folder(prepared, built, logger_names)
    run_loop(prepared, built, loggers, progress)
    return result_of(prepared, built)


def greedy_policy(agent: Any) -> Any:
    """The evaluation policy of an agent (a ``rlu.types.Policy``): ``act(obs, greedy=True)``,
    passing on the episode starts and the previous rewards."""

    def policy(
        observation: Any, is_first: np.ndarray | None = None, reward: np.ndarray | None = None
    ) -> np.ndarray:
        return agent.act(observation, greedy=True, is_first=is_first, reward=reward)

    return policy
