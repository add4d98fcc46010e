"""The one training loop: batch -> agent.update -> periodic evaluation in the env -> logs.

The agent declares its batches (``agent.batch_spec``) and the loop samples exactly those
(``rlu.data.make_sampler``); the run folder's layout and files belong to ``rlu.runs``; how a run
is run (preset, budget, evaluation, checkpoints, runtime) is one ``rlu.settings.RunSettings``.

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
import contextlib
import dataclasses
import json
import os
from collections.abc import Mapping, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rlu import runs
from rlu.devices import compile_modules, numerics
from rlu.files import bounds, check_output, shape_of
from rlu.seeds import derive_seed
from rlu.settings import RunSettings
from rlu.types import ArraySpec, DiscreteSpec, RluError, observation_spec_to_json


@dataclass(frozen=True)
class TrainConfig:
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
    weights: tuple[float, ...] | None = field(default=None, metadata=bounds(metavar="W"))
    """Share of each dataset's samples in a mixture (default: by their sizes)."""

    def __post_init__(self) -> None:
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
        ``fields`` names that field (names in files are never imported)."""
        from rlu.settings import config_from_file

        return config_from_file(cls, os.fspath(path), fields)


# --- agents ---------------------------------------------------------------------------------
def agent_config(name: str, discrete: bool, preset: str, overrides: Mapping[str, Any]) -> Any:
    from rlu.agents import make_config

    return make_config(name, discrete, preset, **overrides)


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """``["learning_rate=3e-4", "hidden=(256, 256)", "atari.batch_size=64"]`` -> typed values
    (Python literals; bare words stay strings; the agent config checks each against its field)."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise RluError(f"override {item!r}; write it as field=value, e.g. learning_rate=3e-4")
        try:
            out[key.strip()] = ast.literal_eval(text.strip())
        except (ValueError, SyntaxError, MemoryError, RecursionError):
            out[key.strip()] = text.strip()
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
    from rlu.tasks import check_challenge

    if not task.startswith("rwrl/"):
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
    ``loggers``: where the metrics go besides the run's own logs (``rlu.loggers.LOGGERS``).
    ``progress``: True shows the steps on stderr (``rlu.progress.Progress``); a
    ``rlu.progress.Relay`` sends them to the process that started this one (a sweep's run).

    One process per run folder: a second ``train`` into the same ``out`` fails with "in use by
    PID N" (:class:`rlu.locks.OutputLock`) while the first lives.
    """
    from rlu.locks import OutputLock

    trust(config.agent, config.run.env)
    with OutputLock(Path(out), "run folder"):
        return _train(config, out, resume, progress, tuple(loggers))


def _train(
    config: TrainConfig,
    out: str | os.PathLike,
    resume: bool,
    progress: bool | Any,
    logger_names: tuple[str, ...],
) -> dict[str, Any]:
    import torch

    from rlu.agents import agent_module
    from rlu.checkpoints import load_state
    from rlu.data import StreamSampler, load_dataset
    from rlu.data.provenance import data_source
    from rlu.data.torch import prefetched
    from rlu.evaluation.rollout import evaluate, task_env_factory
    from rlu.progress import Progress, Relay

    run = Path(out)
    settings = config.run
    runtime = settings.runtime.resolve()
    # a task id, a TFDS name or a folder: the one resolver, once per dataset
    opened = [load_dataset(name) for name in config.datasets()]
    ds = opened[0]  # the evaluation task's; a mixture's others share its schema
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
    resolved = {
        "train": dataclasses.replace(
            config, run=dataclasses.replace(settings, runtime=runtime)
        ).to_json(),
        "env_settings": env_kwargs,
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
    ckpts = runs.checkpoints(run)
    if run.exists() and (run / runs.CONFIG).exists():
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
        if (run / runs.RESULT).exists():  # finished: nothing left to do
            return runs.read_result(run)

    torch.set_num_threads(settings.torch_threads)
    torch.manual_seed(config.seed)
    np.random.seed(config.seed % 2**32)
    module = agent_module(config.agent, discrete)
    agent = module.Agent(obs_spec, action_spec, agent_cfg, seed=config.seed, device=runtime.device)
    sampler = _sampler(config, opened, agent.batch_spec, runtime)
    steps = agent.num_steps if settings.steps is None else int(settings.steps)
    total = agent.pretrain_steps + steps  # a pre-training phase comes on top of the budget

    if agent.batch_spec.statistics and len(opened) > 1:
        raise RluError(
            f"agent {config.agent} normalises by statistics of its dataset "
            f"({', '.join(agent.batch_spec.statistics)}); train it on one dataset"
        )
    if agent.batch_spec.statistics:  # computed from the whole dataset, once, before any update
        from rlu.data.statistics import dataset_statistics

        agent.set_statistics(dataset_statistics(ds, agent.batch_spec.statistics))
    start = 0
    if resume and ckpts:
        state = load_state(ckpts[-1], ("agent", "sampler", "torch_rng", "numpy_rng", "step"))
        start = _restore(ckpts[-1], state, agent, sampler, total)
    # resolved before the first step (a missing rlu.envs fails fast); a run that never evaluates
    # needs no env
    env_fn = None
    eval_period = settings.eval_period(total)
    if eval_period:
        env_fn = task_env_factory(config.task, settings.env, **env_kwargs)
    from rlu.loggers import check_loggers

    check_loggers(logger_names, run, start)  # an unknown one, a bad CSV, a linked folder

    # everything that can fail before the first step has run: only now is the run folder written
    run.mkdir(parents=True, exist_ok=True)
    runs.clear_temporary(run)
    runs.write_json(run / runs.CONFIG, resolved)  # first: a folder with files has its config
    (run / runs.CHECKPOINTS).mkdir(exist_ok=True)
    metrics_path, eval_path = run / runs.METRICS, run / runs.EVAL
    for path in (metrics_path, eval_path):  # drop what was logged after the checkpoint
        runs.cut_log(path, start)
    from rlu.loggers import make_loggers

    loggers = make_loggers(logger_names, run, start, resolved)

    if runtime.compile:
        compile_modules(agent.modules)
    policy = greedy_policy(agent)

    def evaluate_at(step: int) -> dict[str, Any]:
        result = evaluate(
            policy,
            env_fn,
            settings.eval_episodes,
            seed=derive_seed(config.seed, step),  # stream `step` of the run seed
            num_envs=settings.eval_envs,
            max_steps=settings.eval_max_steps,
        )
        record = {"step": step, **result.to_json()}
        elog.write(json.dumps(record) + "\n")
        elog.flush()
        for logger in loggers:
            logger.log("eval", record)
        bar.set_postfix(eval=f"{result.mean:.1f}")
        return record

    if isinstance(progress, Relay):
        display: Any = progress.start(total, initial=start)
    else:
        desc = f"train {config.agent}"
        display = Progress(total, desc, "steps", quiet=not progress, initial=start)
    with (
        display as bar,
        runs.append_log(metrics_path) as mlog,
        runs.append_log(eval_path) as elog,
        numerics(runtime) as update_context,
        contextlib.closing(sampler) if isinstance(sampler, StreamSampler) else nullcontext(),
        prefetched(sampler, runtime.device, runtime.prefetch) as batches,
    ):
        if eval_period and settings.eval_at_start and start == 0:
            evaluate_at(0)
        for step in range(start + 1, total + 1):
            with update_context():
                metrics = agent.update(batches.sample())
            if step % settings.log_every == 0 or step == total:
                rec = {"step": step, **{k: float(v) for k, v in metrics.items()}}
                mlog.write(json.dumps(rec) + "\n")
                mlog.flush()
                for logger in loggers:
                    logger.log("metrics", rec)
            if eval_period and (step % eval_period == 0 or step == total):
                evaluate_at(step)
            if step % settings.checkpoint_every == 0 or step == total:
                alg, keys, pos, has_gauss, cached = np.random.get_state()
                state = {
                    "step": step,
                    "agent": agent.state_dict(),
                    "sampler": batches.get_state(),
                    "torch_rng": torch.get_rng_state(),
                    "numpy_rng": [alg, keys.tolist(), int(pos), int(has_gauss), float(cached)],
                }
                runs.save_checkpoint(run, step, state, settings.keep_checkpoints)
            bar.update(1)
    for logger in loggers:
        logger.close()
    evals = runs.read_log(eval_path, total)
    result = {
        "task": config.task,
        "agent": config.agent,
        "seed": config.seed,
        "preset": settings.preset,
        "steps": steps,
        "pretrain_steps": total - steps,
        "eval_episodes": settings.eval_episodes,
        "data": data_source(ds.manifest),
        "env_settings": env_kwargs,
        "final_eval": evals[-1] if evals else None,
        "score": evals[-1]["mean"] if evals else None,
    }
    runs.write_json(run / runs.RESULT, result)
    return result


def _sampler(config: TrainConfig, datasets: list[Any], spec: Any, runtime: Any) -> Any:
    """The run's batch source (``RunSettings.sampler``): uniform from the one dataset (on the
    device with ``--data-on-device``), or streamed from one or several."""
    from rlu.data import StreamSampler, make_sampler
    from rlu.data.torch import DeviceSampler

    settings = config.run
    kind = settings.sampler
    if kind == "auto":
        kind = "stream" if len(datasets) > 1 else "uniform"
    if kind == "uniform" and len(datasets) > 1:
        raise RluError(
            f"{len(datasets)} datasets: a mixture is streamed; use --sampler stream (or auto)"
        )
    if kind == "stream":
        if runtime.data_on_device:
            raise RluError(
                "--data-on-device holds one dataset on the device for uniform batches; drop it "
                "to stream (--sampler stream: its batches are prefetched)"
            )
        return StreamSampler(datasets, spec, config.seed, config.weights,
                             memory=settings.stream_memory << 20,
                             reuse=settings.stream_reuse)  # fmt: skip
    if config.weights is not None:
        raise RluError("--weights weigh the datasets of a mixture; one dataset needs none")
    if runtime.data_on_device:  # a dataset that does not fit fails here, before any writing
        return DeviceSampler(datasets[0], spec, config.seed, runtime.device)
    return make_sampler(datasets[0], spec, seed=config.seed)


def greedy_policy(agent: Any) -> Any:
    """The evaluation policy of an agent (a ``rlu.types.Policy``): ``act(obs, greedy=True)``,
    passing on the episode starts and the previous rewards."""

    def policy(
        observation: Any, is_first: np.ndarray | None = None, reward: np.ndarray | None = None
    ) -> np.ndarray:
        return agent.act(observation, greedy=True, is_first=is_first, reward=reward)

    return policy


def _restore(path: Path, state: Mapping[str, Any], agent: Any, sampler: Any, total: int) -> int:
    """Load a checkpoint's state into the agent, the sampler and the global generators; returns
    its step. A checkpoint of another agent, of other shapes or with garbage generator states is
    a FormatError naming the file."""
    import torch

    from rlu.types import FormatError

    fix = "resume from a checkpoint this run wrote, or train into a new --out"
    step = state["step"]
    if isinstance(step, bool) or not isinstance(step, int) or not 0 <= step <= total:
        raise FormatError(f"{path}: entry 'step' is {step!r}, not a step of this run; {fix}")
    try:
        agent.load_state_dict(state["agent"])
    except (RuntimeError, KeyError, ValueError, TypeError, AttributeError) as e:
        why = str(e).splitlines()[0][:200] if str(e) else type(e).__name__
        raise FormatError(
            f"{path}: its agent state does not fit this agent ({why}); {fix}"
        ) from None  # noqa: E501
    try:
        sampler.set_state(state["sampler"])
        torch.set_rng_state(state["torch_rng"])
        alg, keys, pos, has_gauss, cached = state["numpy_rng"]
        keys = np.asarray(keys, np.uint32)
        np.random.set_state((alg, keys, int(pos), int(has_gauss), float(cached)))
    except (RuntimeError, KeyError, ValueError, TypeError, AttributeError, OverflowError) as e:
        why = str(e).splitlines()[0][:200] if str(e) else type(e).__name__
        raise FormatError(
            f"{path}: its sampler or generator state is damaged ({why}); {fix}"
        ) from None  # noqa: E501
    return step
