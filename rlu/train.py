"""The one training loop: batch -> agent.update -> periodic evaluation in the env -> logs.

The agent declares its batches (``agent.batch_spec``) and the loop samples exactly those
(``rlu.data.make_sampler``); the run folder's layout and files belong to ``rlu.runs``.

Resume is exact on the CPU: a checkpoint holds the agent's state, the sampler's generator, the
global torch and numpy generators and the step; on ``resume`` the logs are cut back to the
checkpoint's step and the loop goes on. Evaluation at step k uses env seeds derived from
(seed, k) only, so it needs no state.

Agents are built by name through ``rlu.agents`` or, for a dotted module path
(``tests.train.fake_agent``), from any module that follows the agent-module convention
(``Config``, ``Agent``, ``PRESETS``, ``GRID``). Envs come from ``rlu.envs.make_env`` or from an
env factory ``'module:function'`` with the same signature.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import os
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rlu import runs
from rlu.types import ArraySpec, DiscreteSpec, RluError, derive_seed, observation_spec_to_json


@dataclass(frozen=True)
class TrainConfig:
    task: str
    """Task id (the env to evaluate in), e.g. control_suite/cartpole_swingup."""
    agent: str
    """Agent name (rlu.agents) or a dotted module path following the agent-module convention."""
    dataset: str
    """Path of an rlu dataset (``rlu convert`` / ``rlu generate`` output)."""
    preset: str = "small"
    """Agent preset: small (CPU minutes) or paper."""
    steps: int | None = None
    """Gradient steps (None: the agent config's ``num_steps``, its full run)."""
    seed: int = 0
    """Seeds the agent, the sampler and the evaluation episodes."""
    overrides: Mapping[str, Any] = field(default_factory=dict)
    """Agent config fields to change from the preset."""
    eval_every: int = 0
    """Steps between evaluations in the env (0: only at the end; -1: never)."""
    eval_episodes: int = 5
    """Episodes per evaluation."""
    eval_envs: int = 4
    """Envs stepped in lockstep during evaluation."""
    eval_max_steps: int | None = None
    """Cap on an evaluation episode's steps on top of the env's own limit (None: the env's)."""
    log_every: int = 100
    """Steps between lines of metrics.jsonl."""
    checkpoint_every: int = 1000
    """Steps between checkpoints (one is always written at the end)."""
    keep_checkpoints: int = 2
    """Checkpoints kept on disk (the newest)."""
    env: str | None = None
    """Env factory 'module:function' taking (task_id, seed=...); None: rlu.envs.make_env."""
    challenge: str | None = None
    """RWRL tasks: the challenge to evaluate under ('none' / 'easy'); None: the one the dataset
    was recorded under (its provenance's ``challenge``)."""
    torch_threads: int | None = None
    """torch.set_num_threads for this run (None: leave torch's default)."""

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["overrides"] = dict(self.overrides)
        return d


# --- agents ---------------------------------------------------------------------------------
def agent_config(name: str, discrete: bool, preset: str, overrides: Mapping[str, Any]) -> Any:
    from rlu.agents import make_config

    return make_config(name, discrete, preset, **overrides)


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """``["learning_rate=3e-4", "hidden=(256, 256)", "atari.batch_size=64"]`` -> typed values
    (Python literals; bare words stay strings)."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise RluError(f"override {item!r}; write it as field=value, e.g. learning_rate=3e-4")
        try:
            out[key.strip()] = ast.literal_eval(text.strip())
        except (ValueError, SyntaxError):
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
    if not task.startswith("rwrl/"):
        if challenge not in (None, "none"):
            raise RluError(f"--challenge applies to rwrl tasks only; {task} has none")
        return {}
    recorded = ds.manifest["provenance"].get("challenge") or "none"
    chosen = challenge or recorded
    check_challenge(task, chosen, set(dataset_specs(ds)[0]), recorded, str(ds.path))
    return {"challenge": chosen}


def check_challenge(task: str, challenge: str, keys: set[str], recorded: str, what: str) -> None:
    """An RWRL policy runs only where the env gives the observation keys its data had (the easy
    challenge adds dummy observations): refuse a challenge whose keys differ."""
    from rlu.tasks import get_task, rwrl_observation_spec

    wanted = set(rwrl_observation_spec(get_task(task), challenge))
    if wanted != keys:
        differ = sorted(wanted ^ keys)
        raise RluError(
            f"{what} was recorded under RWRL challenge {recorded!r}; challenge {challenge!r} gives "
            f"other observations ({', '.join(differ[:4])}{' ...' if len(differ) > 4 else ''}), so "
            f"its policies cannot run there: evaluate under {recorded!r} (drop --challenge)"
        )


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


class _Progress:
    """A one-line progress bar on stderr (only when it is a terminal)."""

    def __init__(self, total: int, start: int, enabled: bool):
        self.total, self.enabled, self.t0, self.start = total, enabled, time.monotonic(), start

    def update(self, step: int, note: str = "") -> None:
        if not self.enabled or (step % 50 and step != self.total):
            return
        frac = step / max(self.total, 1)
        rate = (step - self.start) / max(time.monotonic() - self.t0, 1e-9)
        bar = "#" * int(30 * frac)
        sys.stderr.write(f"\r[{bar:<30}] {step}/{self.total} {rate:6.1f} steps/s {note}")
        if step == self.total:
            sys.stderr.write("\n")
        sys.stderr.flush()


# --- the loop -------------------------------------------------------------------------------
def train(
    config: TrainConfig,
    out: str | os.PathLike,
    resume: bool = False,
    progress: bool = False,
    tensorboard: bool = False,
) -> dict[str, Any]:
    """Train ``config.agent`` on ``config.dataset``; returns the content of ``result.json``.

    One process per run folder: a second ``train`` into the same ``out`` fails with "in use by
    PID N" (:class:`rlu.locks.OutputLock`) while the first lives.
    """
    from rlu.locks import OutputLock

    with OutputLock(Path(out), "run folder"):
        return _train(config, out, resume, progress, tensorboard)


def _train(
    config: TrainConfig, out: str | os.PathLike, resume: bool, progress: bool, tensorboard: bool
) -> dict[str, Any]:
    import torch

    from rlu.agents import agent_module
    from rlu.data import make_sampler, open_dataset
    from rlu.evaluation.rollout import evaluate, task_env_factory

    run = Path(out)
    ds = open_dataset(config.dataset)
    obs_spec, action_spec = dataset_specs(ds)
    discrete = isinstance(action_spec, DiscreteSpec)
    agent_cfg = agent_config(config.agent, discrete, config.preset, config.overrides)
    env_kwargs = env_settings(config.task, ds, config.challenge)
    resolved = {
        "train": config.to_json(),
        "env_settings": env_kwargs,
        "agent_config": _jsonable(agent_cfg),
        "observation_spec": observation_spec_to_json(obs_spec),
        "action_spec": action_spec.to_json(),
        "dataset": {"path": str(Path(config.dataset).resolve()), "num_steps": int(ds.num_steps)},
    }
    ckpts = runs.checkpoints(run)
    if run.exists() and (run / runs.CONFIG).exists():
        if not resume:
            raise RluError(
                f"{run} already holds a run; pass --resume to continue it or choose a new --out"
            )
        old = runs.read_json(run / runs.CONFIG)
        if old != json.loads(json.dumps(resolved)):
            raise RluError(
                f"{run}/{runs.CONFIG} was written by a different configuration; resume with the "
                "same arguments or choose a new --out"
            )
        if (run / runs.RESULT).exists():  # finished: nothing left to do
            return runs.read_json(run / runs.RESULT)
    if config.env is None and config.eval_every >= 0:
        from rlu.tasks import get_task

        get_task(config.task)  # an unknown task fails here, before the run folder is touched

    if config.torch_threads:
        torch.set_num_threads(config.torch_threads)
    torch.manual_seed(config.seed)
    np.random.seed(config.seed)
    module = agent_module(config.agent, discrete)
    agent = module.Agent(obs_spec, action_spec, agent_cfg, seed=config.seed)
    sampler = make_sampler(ds, agent.batch_spec, seed=config.seed)
    steps = agent.num_steps if config.steps is None else int(config.steps)
    total = agent.pretrain_steps + steps  # a pre-training phase comes on top of the budget

    start = 0
    if resume and ckpts:
        state = runs.load_checkpoint(
            ckpts[-1], ("agent", "sampler", "torch_rng", "numpy_rng", "step")
        )
        agent.load_state_dict(state["agent"])
        sampler.set_state(state["sampler"])
        torch.set_rng_state(state["torch_rng"])
        alg, keys, pos, has_gauss, cached = state["numpy_rng"]
        np.random.set_state((alg, np.asarray(keys, np.uint32), pos, has_gauss, cached))
        start = int(state["step"])
    # resolved before the first step (a missing rlu.envs fails fast); a run that never evaluates
    # needs no env
    env_fn = None
    if config.eval_every >= 0:
        env_fn = task_env_factory(config.task, config.env, **env_kwargs)
    summary_writer: Any = None
    if tensorboard:
        try:
            from torch.utils.tensorboard import SummaryWriter

            summary_writer = SummaryWriter
        except ImportError:
            raise RluError(
                "TensorBoard logging needs the tensorboard package: pip install tensorboard"
            ) from None

    # everything that can fail before the first step has run: only now is the run folder written
    run.mkdir(parents=True, exist_ok=True)
    (run / runs.CHECKPOINTS).mkdir(exist_ok=True)
    for tmp in run.rglob("*.tmp"):
        tmp.unlink()
    runs.write_json(run / runs.CONFIG, resolved)
    metrics_path, eval_path = run / runs.METRICS, run / runs.EVAL
    for path in (metrics_path, eval_path):  # drop what was logged after the checkpoint
        runs.cut_log(path, start)
    writer = summary_writer(str(run / "tensorboard")) if summary_writer is not None else None

    policy = runs.greedy_policy(agent)
    eval_every = config.eval_every if config.eval_every > 0 else total
    bar = _Progress(total, start, progress and sys.stderr.isatty())
    last_eval: dict[str, Any] | None = None
    with open(metrics_path, "a") as mlog, open(eval_path, "a") as elog:
        for step in range(start + 1, total + 1):
            metrics = agent.update(sampler.sample())
            if step % config.log_every == 0 or step == total:
                rec = {"step": step, **{k: float(v) for k, v in metrics.items()}}
                mlog.write(json.dumps(rec) + "\n")
                mlog.flush()
                if writer is not None:
                    for k, v in metrics.items():
                        writer.add_scalar(k, float(v), step)
            if config.eval_every >= 0 and (step % eval_every == 0 or step == total):
                result = evaluate(
                    policy,
                    env_fn,
                    config.eval_episodes,
                    seed=derive_seed(config.seed, step),  # stream `step` of the run seed
                    num_envs=config.eval_envs,
                    max_steps=config.eval_max_steps,
                )
                last_eval = {"step": step, **result.to_json()}
                elog.write(json.dumps(last_eval) + "\n")
                elog.flush()
                if writer is not None:
                    writer.add_scalar("eval/return", result.mean, step)
            if step % config.checkpoint_every == 0 or step == total:
                alg, keys, pos, has_gauss, cached = np.random.get_state()
                state = {
                    "step": step,
                    "agent": agent.state_dict(),
                    "sampler": sampler.get_state(),
                    "torch_rng": torch.get_rng_state(),
                    "numpy_rng": [alg, keys.tolist(), int(pos), int(has_gauss), float(cached)],
                }
                runs.save_checkpoint(run, step, state, config.keep_checkpoints)
            bar.update(step, f"eval {last_eval['mean']:.1f}" if last_eval else "")
    if writer is not None:
        writer.close()
    evals = runs.read_jsonl(eval_path, total)
    result = {
        "task": config.task,
        "agent": config.agent,
        "seed": config.seed,
        "steps": steps,
        "pretrain_steps": total - steps,
        "env_settings": env_kwargs,
        "final_eval": evals[-1] if evals else None,
        "score": evals[-1]["mean"] if evals else None,
    }
    runs.write_json(run / runs.RESULT, result)
    return result
