"""A run before its first step: every check and every resolution of a ``TrainConfig``, giving one
:class:`Prepared` value that the loop (``rlu.training.loop``) reads and never changes.

What is resolved here: the datasets (``rlu.load_dataset``, once each), the output folder
against them (``rlu.files.check_output``), the specs the agent sees, the agent's config from its
preset and overrides, the evaluation env's settings, the data against the task, and the run's
resolved config (config.json). A run folder that already holds a run is checked against it:
``resume`` must be asked for and the configuration must be the same (``comparable``); a
finished run comes back as its result. Nothing is written here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rlu.devices import Runtime
from rlu.files import check_output
from rlu.training import runs
from rlu.training.config import RunSettings
from rlu.training.train import (
    TrainConfig,
    _jsonable,
    agent_config,
    comparable,
    dataset_specs,
    env_settings,
)
from rlu.types import (
    ArraySpec,
    DiscreteSpec,
    ObservationSpec,
    RluError,
    observation_spec_to_json,
)


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
