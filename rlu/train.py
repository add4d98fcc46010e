"""The one training loop: batch -> agent.update -> periodic evaluation in the env -> logs.

A run folder holds ``config.json`` (the resolved run and agent config), ``metrics.jsonl`` (the
agent's update metrics every ``log_every`` steps), ``eval.jsonl`` (one line per evaluation: step,
episode returns), ``checkpoints/step_XXXXXXXX.pt`` and, once finished, ``result.json``.

Resume is exact on the CPU: a checkpoint holds the agent's state, the sampler's generator, the
global torch and numpy generators and the step; on ``resume`` the logs are cut back to the
checkpoint's step and the loop goes on. Evaluation at step k uses env seeds derived from
(seed, k) only, so it needs no state. Checkpoints and ``result.json`` are written to a temporary
name and renamed, so a kill leaves either the old file or the new one.

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

from rlu.checkpoints import load_checkpoint
from rlu.types import ArraySpec, DiscreteSpec, RluError, observation_spec_to_json


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
    steps: int = 1000
    """Gradient steps."""
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
    torch_threads: int | None = None
    """torch.set_num_threads for this run (None: leave torch's default)."""

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["overrides"] = dict(self.overrides)
        return d


# --- agents ---------------------------------------------------------------------------------
def agent_module(name: str, discrete: bool) -> Any:
    from rlu.agents import agent_module as registry_module

    return registry_module(name, discrete)


def agent_config(name: str, discrete: bool, preset: str, overrides: Mapping[str, Any]) -> Any:
    from rlu.agents import make_config

    return make_config(name, discrete, preset, **overrides)


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """``["learning_rate=3e-4", "hidden=(256, 256)"]`` -> typed values (Python literals; bare
    words stay strings)."""
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


def _gamma(agent_cfg: Any) -> float:
    """The agent's discount for n-step views: its config's ``gamma`` (or ``discount``) field."""
    for name in ("gamma", "discount"):
        if hasattr(agent_cfg, name):
            return float(getattr(agent_cfg, name))
    raise RluError(
        f"{type(agent_cfg).__name__} has n_step > 1 but no gamma field; add `gamma: float` to "
        "the agent's config so the loop can build n-step targets"
    )


def dataset_specs(ds: Any) -> tuple[Any, Any]:
    """(observation spec as the agent sees it, action spec) from a dataset's schema."""
    schema = ds.schema
    obs = schema.observation
    if schema.frame_stack > 1:
        obs = ArraySpec((*obs.shape, schema.frame_stack), obs.dtype)
    return obs, schema.action


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


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _read_jsonl(path: Path, max_step: int) -> list[str]:
    """Complete lines with step <= max_step (a kill can leave a torn last line)."""
    if not path.exists():
        return []
    keep = []
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if int(rec["step"]) <= max_step:
            keep.append(line)
    return keep


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
def _checkpoints(run: Path) -> list[Path]:
    return sorted((run / "checkpoints").glob("step_*.pt"))


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

    from rlu.data import open_dataset
    from rlu.data.views import Sampler, SequenceView, TransitionView
    from rlu.evaluation.rollout import evaluate, task_env_factory

    run = Path(out)
    ds = open_dataset(config.dataset)
    obs_spec, action_spec = dataset_specs(ds)
    discrete = isinstance(action_spec, DiscreteSpec)
    agent_cfg = agent_config(config.agent, discrete, config.preset, config.overrides)
    resolved = {
        "train": config.to_json(),
        "agent_config": _jsonable(agent_cfg),
        "observation_spec": observation_spec_to_json(obs_spec),
        "action_spec": action_spec.to_json(),
        "dataset": {"path": str(Path(config.dataset).resolve()), "num_steps": int(ds.num_steps)},
    }
    ckpts = _checkpoints(run)
    if run.exists() and (run / "config.json").exists():
        if not resume:
            raise RluError(
                f"{run} already holds a run; pass --resume to continue it or choose a new --out"
            )
        old = json.loads((run / "config.json").read_text())
        if old != json.loads(json.dumps(resolved)):
            raise RluError(
                f"{run}/config.json was written by a different configuration; resume with the "
                "same arguments or choose a new --out"
            )
        if (run / "result.json").exists():  # finished: nothing left to do
            return json.loads((run / "result.json").read_text())
    if config.env is None and config.eval_every >= 0:
        from rlu.tasks import get_task

        get_task(config.task)  # an unknown task fails here, before the run folder is touched

    if config.torch_threads:
        torch.set_num_threads(config.torch_threads)
    torch.manual_seed(config.seed)
    np.random.seed(config.seed)
    module = agent_module(config.agent, discrete)
    agent = module.Agent(obs_spec, action_spec, agent_cfg, seed=config.seed)
    if agent.batch_kind == "sequence":
        view: Any = SequenceView(ds, agent.sequence_length)
    else:
        n_step = int(getattr(agent, "n_step", 1))
        view = TransitionView(ds, n_step, _gamma(agent_cfg) if n_step > 1 else 1.0)
    batch_size = int(getattr(agent_cfg, "batch_size", 256))
    sampler = Sampler(view, batch_size, seed=config.seed)

    start = 0
    if resume and ckpts:
        state = load_checkpoint(ckpts[-1], ("agent", "sampler", "torch_rng", "numpy_rng", "step"))
        agent.load_state_dict(state["agent"])
        sampler.set_state(state["sampler"])
        torch.set_rng_state(state["torch_rng"])
        alg, keys, pos, has_gauss, cached = state["numpy_rng"]
        np.random.set_state((alg, np.asarray(keys, np.uint32), pos, has_gauss, cached))
        start = int(state["step"])
    # resolved before the first step (a missing rlu.envs fails fast); a run that never evaluates
    # needs no env
    env_fn = task_env_factory(config.task, config.env) if config.eval_every >= 0 else None
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
    (run / "checkpoints").mkdir(exist_ok=True)
    for tmp in run.rglob("*.tmp"):
        tmp.unlink()
    _write_atomic(run / "config.json", json.dumps(resolved, indent=2) + "\n")
    metrics_path, eval_path = run / "metrics.jsonl", run / "eval.jsonl"
    for path in (metrics_path, eval_path):  # drop what was logged after the checkpoint
        lines = _read_jsonl(path, start)
        _write_atomic(path, "".join(line + "\n" for line in lines))
    writer = summary_writer(str(run / "tensorboard")) if summary_writer is not None else None

    def policy(obs: Any) -> np.ndarray:
        return agent.act(obs, greedy=True)

    eval_every = config.eval_every if config.eval_every > 0 else config.steps
    bar = _Progress(config.steps, start, progress and sys.stderr.isatty())
    last_eval: dict[str, Any] | None = None
    with open(metrics_path, "a") as mlog, open(eval_path, "a") as elog:
        for step in range(start + 1, config.steps + 1):
            metrics = agent.update(sampler.sample())
            if step % config.log_every == 0 or step == config.steps:
                rec = {"step": step, **{k: float(v) for k, v in metrics.items()}}
                mlog.write(json.dumps(rec) + "\n")
                mlog.flush()
                if writer is not None:
                    for k, v in metrics.items():
                        writer.add_scalar(k, float(v), step)
            if config.eval_every >= 0 and (step % eval_every == 0 or step == config.steps):
                result = evaluate(
                    policy,
                    env_fn,
                    config.eval_episodes,
                    seed=(config.seed + 1) * 1_000_003 + step * 1_009,
                    num_envs=config.eval_envs,
                    max_steps=config.eval_max_steps,
                )
                last_eval = {"step": step, **result.to_json()}
                elog.write(json.dumps(last_eval) + "\n")
                elog.flush()
                if writer is not None:
                    writer.add_scalar("eval/return", result.mean, step)
            if step % config.checkpoint_every == 0 or step == config.steps:
                _save_checkpoint(run, step, agent, sampler, config.keep_checkpoints)
            bar.update(step, f"eval {last_eval['mean']:.1f}" if last_eval else "")
    if writer is not None:
        writer.close()
    evals = [json.loads(x) for x in _read_jsonl(eval_path, config.steps)]
    result = {
        "task": config.task,
        "agent": config.agent,
        "seed": config.seed,
        "steps": config.steps,
        "final_eval": evals[-1] if evals else None,
        "score": evals[-1]["mean"] if evals else None,
    }
    _write_atomic(run / "result.json", json.dumps(result, indent=2) + "\n")
    return result


def _save_checkpoint(run: Path, step: int, agent: Any, sampler: Any, keep: int) -> None:
    import torch

    alg, keys, pos, has_gauss, cached = np.random.get_state()
    state = {
        "step": step,
        "agent": agent.state_dict(),
        "sampler": sampler.get_state(),
        "torch_rng": torch.get_rng_state(),
        "numpy_rng": [alg, keys.tolist(), int(pos), int(has_gauss), float(cached)],
    }
    path = run / "checkpoints" / f"step_{step:08d}.pt"
    tmp = path.with_name(path.name + ".tmp")
    torch.save(state, tmp)
    with open(tmp, "rb+") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)
    for old in _checkpoints(run)[:-keep] if keep > 0 else []:
        old.unlink()


def load_run(path: str | os.PathLike) -> tuple[dict[str, Any], Path]:
    """(resolved config, checkpoint path) of a run folder or of one checkpoint file in it."""
    p = Path(path)
    if p.is_file():
        ckpt, run = p, p.parent.parent
    else:
        run = p
        ckpts = _checkpoints(run)
        if not ckpts:
            raise RluError(f"{run} has no checkpoints/step_*.pt; train it first (rlu train)")
        ckpt = ckpts[-1]
    cfg_path = run / "config.json"
    if not cfg_path.exists():
        raise RluError(f"{cfg_path} is missing; {path} is not an rlu run folder or checkpoint")
    try:
        return json.loads(cfg_path.read_text()), ckpt
    except (ValueError, UnicodeDecodeError) as e:
        raise RluError(f"{cfg_path}: not a run's JSON config ({e}); re-train the run") from None


def load_policy(path: str | os.PathLike) -> tuple[Any, dict[str, Any]]:
    """(greedy policy callable on batched observations, resolved config) of a run folder's newest
    checkpoint, or of a given checkpoint file."""
    from rlu.types import ArraySpec as _AS
    from rlu.types import observation_spec_from_json

    cfg, ckpt = load_run(path)
    train_cfg = cfg["train"]
    obs_spec = observation_spec_from_json(cfg["observation_spec"])
    action_spec = _AS.from_json(cfg["action_spec"])
    discrete = isinstance(action_spec, DiscreteSpec)
    module = agent_module(train_cfg["agent"], discrete)
    fields = {f.name for f in dataclasses.fields(module.Config)}
    agent_cfg = agent_config(
        train_cfg["agent"],
        discrete,
        train_cfg["preset"],
        {k: v for k, v in cfg["agent_config"].items() if k in fields},
    )
    agent = module.Agent(obs_spec, action_spec, agent_cfg, seed=int(train_cfg["seed"]))
    agent.load_state_dict(load_checkpoint(ckpt, ("agent",))["agent"])

    def policy(obs: Any) -> np.ndarray:
        return agent.act(obs, greedy=True)

    return policy, cfg


def evaluate_run(
    path: str | os.PathLike,
    episodes: int = 10,
    seed: int = 0,
    num_envs: int = 4,
    env: str | None = None,
    max_steps: int | None = None,
) -> Any:
    """Roll out the greedy policy of a run folder's newest checkpoint (or a given checkpoint)."""
    from rlu.evaluation.rollout import evaluate, task_env_factory

    policy, cfg = load_policy(path)
    train_cfg = cfg["train"]
    env_fn = task_env_factory(train_cfg["task"], env if env is not None else train_cfg["env"])
    return evaluate(policy, env_fn, episodes, seed, num_envs, max_steps)


def fqe_selection(sweep_dir: str | os.PathLike, config: Any = None) -> dict[str, Any]:
    """Offline policy selection by FQE over a finished sweep: per (task, agent), every
    configuration's policy (each seed's run) is valued by FQE on the task's dataset (data only);
    the configuration with the best mean estimate is chosen and scored against the true returns
    (Spearman rank correlation, regret@1). Writes and returns ``SWEEP_DIR/fqe.json``."""
    from collections import defaultdict

    from rlu.data import open_dataset
    from rlu.evaluation.fqe import FQEConfig, dataset_fqe_inputs, fqe_estimate
    from rlu.evaluation.protocols import select_by_estimate
    from rlu.sweep import load_results
    from rlu.types import ArraySpec as _AS

    sweep_dir = Path(sweep_dir)
    config = config or FQEConfig()
    records = load_results(sweep_dir)
    datasets = json.loads((sweep_dir / "sweep.json").read_text())["datasets"]
    groups: dict[tuple[str, str], dict[str, list[dict[str, Any]]]] = defaultdict(
        lambda: defaultdict(list)
    )
    for r in records:
        groups[(r["task"], r["agent"])][r["config"]].append(r)
    inputs: dict[str, Any] = {}
    out: dict[str, Any] = {"fqe_config": dataclasses.asdict(config), "selections": []}
    for (task, agent), by_cfg in sorted(groups.items()):
        if task not in inputs:
            inputs[task] = dataset_fqe_inputs(open_dataset(datasets[task]))
        transitions, init = inputs[task]
        estimates, true = {}, {}
        for label, runs in sorted(by_cfg.items()):
            values = []
            for r in runs:
                policy, cfg = load_policy(r["run"])
                spec = _AS.from_json(cfg["action_spec"])
                values.append(fqe_estimate(transitions, init, policy, spec, config))
            estimates[label] = float(np.mean(values))
            true[label] = float(np.mean([r["score"] for r in runs]))
        sel = select_by_estimate(estimates, true)
        out["selections"].append(
            {
                "task": task,
                "agent": agent,
                "estimates": estimates,
                "true_returns": true,
                **dataclasses.asdict(sel),
            }
        )
    _write_atomic(sweep_dir / "fqe.json", json.dumps(out, indent=2) + "\n")
    return out
