"""The loop of a prepared run (``rlu.training.prepare``): build the agent and its batch source,
write the run folder, then update -> log -> evaluate -> checkpoint until the budget is spent,
and the result.

Resume is exact on the CPU: a checkpoint holds the agent's state, the sampler's generator, the
global torch and numpy generators and the step; on resume the logs are cut back to the
checkpoint's step and the loop goes on. Evaluation at step k uses env seeds derived from
(seed, k) only, so it needs no state. Every metric and evaluation record goes through the run's
loggers (``rlu.training.loggers``): the run's own JSONL logs and those the user asked for.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Mapping, Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rlu.devices import compile_modules, numerics
from rlu.seeds import derive_seed, stream_seed
from rlu.training import runs
from rlu.training.prepare import Prepared, TrainConfig
from rlu.types import RluError


@dataclass(frozen=True)
class Built:
    """What a prepared run trains with."""

    agent: Any
    sampler: Any
    steps: int
    """The learner budget (``--steps`` or the preset's)."""
    total: int
    """Pre-training steps and the budget: the loop's last step."""
    start: int
    """The step the loop continues from (0, or the resumed checkpoint's)."""
    env_fn: Any
    """The evaluation env factory (None: the run never evaluates)."""
    eval_period: int


def build(p: Prepared, logger_names: Sequence[str]) -> Built:
    """The agent (seeded), its sampler, statistics and the resumed state, the evaluation env
    factory; checks the logger names. Nothing is written."""
    import torch

    from rlu.agents import agent_module
    from rlu.evaluation.rollout import task_env_factory
    from rlu.training.checkpoints import load_state
    from rlu.training.loggers import check_loggers

    config, settings = p.config, p.settings
    torch.set_num_threads(settings.torch_threads)
    torch.manual_seed(config.seed)
    np.random.seed(config.seed % 2**32)
    module = agent_module(config.agent, p.discrete)
    agent = module.Agent(
        p.obs_spec, p.action_spec, p.agent_cfg, seed=config.seed, device=p.runtime.device
    )
    sampler = _sampler(config, p.opened, agent.batch_spec, p.runtime)
    steps = agent.num_steps if settings.steps is None else int(settings.steps)
    total = agent.pretrain_steps + steps  # a pre-training phase comes on top of the budget
    if agent.batch_spec.statistics and len(p.opened) > 1:
        raise RluError(
            f"agent {config.agent} normalises by statistics of its dataset "
            f"({', '.join(agent.batch_spec.statistics)}); train it on one dataset"
        )
    if agent.batch_spec.statistics:  # computed from the whole dataset, once, before any update
        from rlu.data.statistics import dataset_statistics

        agent.set_statistics(dataset_statistics(p.dataset, agent.batch_spec.statistics))
    start = 0
    if p.checkpoints:  # resumed (prepare lists the checkpoints only on resume)
        last = p.checkpoints[-1]
        state = load_state(last, ("agent", "sampler", "torch_rng", "numpy_rng", "step"))
        start = _restore(last, state, agent, sampler, total)
    # resolved before the first step (a missing rlu.envs fails fast); a run that never
    # evaluates needs no env
    eval_period = settings.eval_period(total)
    env_fn = task_env_factory(config.task, settings.env, **p.env_kwargs) if eval_period else None
    check_loggers(tuple(logger_names), p.run, start)  # an unknown one, a bad CSV, a linked folder
    return Built(agent, sampler, steps, total, start, env_fn, eval_period)


def start_folder(p: Prepared, b: Built, logger_names: Sequence[str]) -> list[Any]:
    """Write the run folder's config and cut its logs back to the resumed step; the loggers."""
    from rlu.training.loggers import make_loggers

    run = p.run
    run.mkdir(parents=True, exist_ok=True)
    runs.clear_temporary(run)
    runs.write_json(run / runs.CONFIG, p.resolved)  # first: a folder with files has its config
    (run / runs.CHECKPOINTS).mkdir(exist_ok=True)
    for path in (run / runs.METRICS, run / runs.EVAL):  # what was logged after the checkpoint
        runs.cut_log(path, b.start)
    return make_loggers(tuple(logger_names), run, b.start, p.resolved)


def _display(p: Prepared, b: Built, progress: bool | Any) -> Any:
    from rlu.progress import Progress, Relay

    if isinstance(progress, Relay):
        return progress.start(b.total, initial=b.start)
    desc = f"train {p.config.agent}"
    return Progress(b.total, desc, "steps", quiet=not progress, initial=b.start)


def run_loop(p: Prepared, b: Built, loggers: Sequence[Any], progress: bool | Any) -> None:
    """Update from ``b.start + 1`` to ``b.total``, logging, evaluating and checkpointing."""
    from rlu.data import StreamSampler
    from rlu.data.torch import prefetched
    from rlu.evaluation.rollout import evaluate

    settings, runtime, agent = p.settings, p.runtime, b.agent
    assert runtime.prefetch is not None  # Runtime.resolve decided it (prepare)
    if runtime.compile:
        compile_modules(agent.modules)
    policy = greedy_policy(agent)

    def evaluate_at(step: int) -> None:
        result = evaluate(
            policy,
            b.env_fn,
            settings.eval_episodes,
            seed=derive_seed(p.config.seed, step),  # stream `step` of the run seed
            num_envs=settings.eval_envs,
            max_steps=settings.eval_max_steps,
        )
        _log(elog, loggers, "eval", {"step": step, **result.to_json()})
        bar.set_postfix(eval=f"{result.mean:.1f}")

    streamed = isinstance(b.sampler, StreamSampler)
    with (
        _display(p, b, progress) as bar,
        runs.append_log(p.run / runs.METRICS) as mlog,
        runs.append_log(p.run / runs.EVAL) as elog,
        numerics(runtime) as update_context,
        contextlib.closing(b.sampler) if streamed else nullcontext(),
        prefetched(b.sampler, runtime.device, runtime.prefetch) as batches,
    ):
        if b.eval_period and settings.eval_at_start and b.start == 0:
            evaluate_at(0)
        for step in range(b.start + 1, b.total + 1):
            with update_context():
                metrics = agent.update(batches.sample())
            last = step == b.total
            if step % settings.log_every == 0 or last:
                rec = {"step": step, **{k: float(v) for k, v in metrics.items()}}
                _log(mlog, loggers, "metrics", rec)
            if b.eval_period and (step % b.eval_period == 0 or last):
                evaluate_at(step)
            if step % settings.checkpoint_every == 0 or last:
                state = _checkpoint_state(step, agent, batches)
                runs.save_checkpoint(p.run, step, state, settings.keep_checkpoints)
            bar.update(1)
    for logger in loggers:
        logger.close()


def _log(log: Any, loggers: Sequence[Any], kind: str, record: Mapping[str, Any]) -> None:
    """One record into the run's own JSONL log and every logger."""
    log.write(json.dumps(record) + "\n")
    log.flush()
    for logger in loggers:
        logger.log(kind, record)


def _checkpoint_state(step: int, agent: Any, batches: Any) -> dict[str, Any]:
    import torch

    numpy_state = np.random.get_state()
    assert isinstance(numpy_state, tuple)  # legacy=True: MT19937's five fields
    alg, keys, pos, has_gauss, cached = numpy_state
    return {
        "step": step,
        "agent": agent.state_dict(),
        "sampler": batches.get_state(),
        "torch_rng": torch.get_rng_state(),
        "numpy_rng": [alg, keys.tolist(), int(pos), int(has_gauss), float(cached)],
    }


def result_of(p: Prepared, b: Built) -> dict[str, Any]:
    """Write and return result.json: the final evaluation and what produced it."""
    from rlu.data.provenance import data_source

    config, settings = p.config, p.settings
    evals = runs.read_log(p.run / runs.EVAL, b.total)
    result = {
        "task": config.task,
        "agent": config.agent,
        "seed": config.seed,
        "preset": settings.preset,
        "steps": b.steps,
        "pretrain_steps": b.total - b.steps,
        "eval_episodes": settings.eval_episodes,
        "data": data_source(p.dataset.manifest),
        "env_settings": dict(p.env_kwargs),
        "final_eval": evals[-1] if evals else None,
        "score": evals[-1]["mean"] if evals else None,
    }
    runs.write_json(p.run / runs.RESULT, result)
    return result


def _sampler(config: TrainConfig, datasets: Sequence[Any], spec: Any, runtime: Any) -> Any:
    """The run's batch source (``RunSettings.sampler``): uniform from the one dataset (on the
    device with ``--data-on-device``), or streamed from one or several; its seed is the run's
    ``sampler`` stream (``rlu.seeds.stream_seed``)."""
    from rlu.data import StreamSampler, make_sampler
    from rlu.data.torch import DeviceSampler

    settings, seed = config.run, stream_seed(config.seed, "sampler")
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
        return StreamSampler(datasets, spec, seed, config.weights,
                             memory=settings.stream_memory << 20,
                             reuse=settings.stream_reuse)  # fmt: skip
    if config.weights is not None:
        raise RluError("--weights weigh the datasets of a mixture; one dataset needs none")
    if runtime.data_on_device:  # a dataset that does not fit fails here, before any writing
        return DeviceSampler(datasets[0], spec, seed, runtime.device)
    return make_sampler(datasets[0], spec, seed=seed)


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


def greedy_policy(agent: Any) -> Any:
    """The evaluation policy of an agent (a ``rlu.types.Policy``): ``act(obs, greedy=True)``,
    passing on the episode starts and the previous rewards."""

    def policy(
        observation: Any, is_first: np.ndarray | None = None, reward: np.ndarray | None = None
    ) -> np.ndarray:
        return agent.act(observation, greedy=True, is_first=is_first, reward=reward)

    return policy
