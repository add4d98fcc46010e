"""Run and sweep folders: the one module that knows their layout, writes them atomically and
reads them back (a finished run's policy included).

A run folder (``rlu train --out RUN``)::

    config.json        the resolved run config, agent config and specs (written once)
    metrics.jsonl      the agent's update metrics, one line every ``log_every`` steps
    eval.jsonl         one line per evaluation: step, episode returns and lengths
    checkpoints/       step_XXXXXXXX.pt: agent state, sampler and RNG states (weights_only)
    result.json        written last, when the run is finished

A sweep folder (``rlu sweep --out SWEEP``)::

    sweep.json         the sweep config
    results.jsonl      one record per finished run (task, agent, config, seed, score, run)
    <task>/<agent>/<config>/seed_<s>/   the run folders
    fqe.json           offline selection by FQE (``rlu report --fqe``)

Every file is written to a temporary name, synced and renamed, so a kill leaves either the old
file or the new one; the ``.jsonl`` logs are appended line by line and cut back to the last
checkpoint on resume (a torn last line is dropped).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rlu.types import ArraySpec, DiscreteSpec, FormatError, RluError, observation_spec_from_json

CONFIG = "config.json"
METRICS = "metrics.jsonl"
EVAL = "eval.jsonl"
RESULT = "result.json"
CHECKPOINTS = "checkpoints"
SWEEP_CONFIG = "sweep.json"
RESULTS = "results.jsonl"
FQE = "fqe.json"


# --- files ----------------------------------------------------------------------------------
def write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def write_json(path: Path, data: Any) -> None:
    write_atomic(path, json.dumps(data, indent=2) + "\n")


def read_json(path: Path) -> Any:
    """A JSON file rlu wrote (run config, result, sweep config), or a clear error if it is not."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise FormatError(
            f"{path}: not a readable JSON file ({type(e).__name__}: {e}); rlu writes it whole "
            "(temporary file + rename), so it was damaged or replaced: restore it or rerun the "
            "command that wrote it into a new folder"
        ) from None


def read_jsonl(path: Path, max_step: int | None = None) -> list[dict[str, Any]]:
    """Complete records (with ``step <= max_step`` when given); a kill can leave a torn line."""
    if not path.exists():
        return []
    keep = []
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        if max_step is None or int(record["step"]) <= max_step:
            keep.append(record)
    return keep


def cut_log(path: Path, max_step: int) -> None:
    """Keep the lines of ``path`` logged at or before ``max_step`` (resume from a checkpoint)."""
    write_atomic(path, "".join(json.dumps(r) + "\n" for r in read_jsonl(path, max_step)))


# --- run folders ----------------------------------------------------------------------------
def checkpoints(run: Path) -> list[Path]:
    return sorted((Path(run) / CHECKPOINTS).glob("step_*.pt"))


def save_checkpoint(run: Path, step: int, state: Mapping[str, Any], keep: int) -> Path:
    """Write ``state`` as ``checkpoints/step_XXXXXXXX.pt`` atomically; keep the newest ``keep``."""
    import torch

    path = Path(run) / CHECKPOINTS / f"step_{step:08d}.pt"
    tmp = path.with_name(path.name + ".tmp")
    torch.save(dict(state), tmp)
    with open(tmp, "rb+") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)
    for old in checkpoints(run)[:-keep] if keep > 0 else []:
        old.unlink()
    return path


def load_checkpoint(path: Path, keys: tuple[str, ...] = ("agent",)) -> dict[str, Any]:
    """A checkpoint's content, loaded without unpickling anything but tensors and plain data;
    a damaged, empty or planted file is a FormatError naming it (:mod:`rlu.checkpoints`)."""
    from rlu.checkpoints import load_checkpoint as load

    return load(path, keys)


def load_run(path: str | os.PathLike) -> tuple[dict[str, Any], Path]:
    """(resolved config, checkpoint path) of a run folder (its newest checkpoint) or of one
    checkpoint file in it."""
    p = Path(path)
    if p.is_file():
        ckpt, run = p, p.parent.parent
    else:
        run = p
        found = checkpoints(run)
        if not found:
            raise RluError(f"{run} has no {CHECKPOINTS}/step_*.pt; train it first (rlu train)")
        ckpt = found[-1]
    cfg_path = run / CONFIG
    if not cfg_path.exists():
        raise RluError(f"{cfg_path} is missing; {path} is not an rlu run folder or checkpoint")
    return read_json(cfg_path), ckpt


def build_agent(resolved: Mapping[str, Any]) -> Any:
    """The agent a run's resolved config describes, freshly initialised (config, specs, seed)."""
    from rlu.agents import agent_module, config_from_json

    train_cfg = resolved["train"]
    obs_spec = observation_spec_from_json(resolved["observation_spec"])
    action_spec = ArraySpec.from_json(resolved["action_spec"])
    module = agent_module(train_cfg["agent"], isinstance(action_spec, DiscreteSpec))
    config = config_from_json(module.Config, resolved["agent_config"])
    return module.Agent(obs_spec, action_spec, config, seed=int(train_cfg["seed"]))


def load_agent(path: str | os.PathLike) -> tuple[Any, dict[str, Any]]:
    """(agent restored from a run's newest checkpoint or a given checkpoint, resolved config)."""
    resolved, ckpt = load_run(path)
    agent = build_agent(resolved)
    agent.load_state_dict(load_checkpoint(ckpt)["agent"])
    return agent, resolved


def greedy_policy(agent: Any) -> Any:
    """The evaluation policy of an agent (a ``rlu.types.Policy``): ``act(obs, greedy=True)``."""

    def policy(observation: Any, is_first: np.ndarray | None = None) -> np.ndarray:
        return agent.act(observation, greedy=True, is_first=is_first)

    return policy


def load_policy(path: str | os.PathLike) -> tuple[Any, dict[str, Any]]:
    """(greedy policy of a run's newest checkpoint or of a given checkpoint, resolved config)."""
    agent, resolved = load_agent(path)
    return greedy_policy(agent), resolved


def evaluate_run(
    path: str | os.PathLike,
    episodes: int = 10,
    seed: int = 0,
    num_envs: int = 4,
    env: str | None = None,
    max_steps: int | None = None,
    challenge: str | None = None,
) -> Any:
    """Roll out the greedy policy of a run folder's newest checkpoint (or a given checkpoint) in
    the env the run evaluated in (an RWRL run: its data's challenge, unless ``challenge``)."""
    from rlu.evaluation.rollout import evaluate, task_env_factory

    policy, resolved = load_policy(path)
    train_cfg = resolved["train"]
    settings = dict(resolved["env_settings"])
    if challenge is not None:
        if "challenge" not in settings:
            raise RluError(f"--challenge applies to rwrl runs only; {path} is {train_cfg['task']}")
        from rlu.train import check_challenge

        keys = set(resolved["observation_spec"])
        check_challenge(train_cfg["task"], challenge, keys, settings["challenge"], str(path))
        settings["challenge"] = challenge
    factory = env if env is not None else train_cfg["env"]
    env_fn = task_env_factory(train_cfg["task"], factory, **settings)
    return evaluate(policy, env_fn, episodes, seed, num_envs, max_steps)


# --- sweep folders --------------------------------------------------------------------------
def load_sweep_config(sweep_dir: str | os.PathLike) -> dict[str, Any]:
    path = Path(sweep_dir) / SWEEP_CONFIG
    if not path.exists():
        raise RluError(f"{path} is missing; {sweep_dir} is not a sweep folder (rlu sweep --out)")
    return read_json(path)


def load_results(sweep_dir: str | os.PathLike) -> list[dict[str, Any]]:
    path = Path(sweep_dir) / RESULTS
    if not path.exists():
        raise RluError(f"{path} is missing; run the sweep first (rlu sweep ... --out {sweep_dir})")
    records = []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as e:
            raise FormatError(
                f"{path}: line {i} is not JSON ({e}); rerun the sweep (it rewrites this file from "
                "its finished runs)"
            ) from None
    return records


def write_results(sweep_dir: str | os.PathLike, records: Sequence[Mapping[str, Any]]) -> None:
    text = "".join(json.dumps(r) + "\n" for r in records)
    write_atomic(Path(sweep_dir) / RESULTS, text)


def fqe_selection(sweep_dir: str | os.PathLike, config: Any = None) -> dict[str, Any]:
    """Offline policy selection by FQE over a finished sweep (see
    ``rlu.evaluation.fqe.fqe_selection``); writes and returns ``SWEEP_DIR/fqe.json``."""
    from rlu.evaluation.fqe import FQEConfig
    from rlu.evaluation.fqe import fqe_selection as select

    config = config or FQEConfig()
    datasets = load_sweep_config(sweep_dir)["datasets"]

    def policy_of(run: str) -> tuple[Any, Any]:
        policy, resolved = load_policy(run)
        return policy, ArraySpec.from_json(resolved["action_spec"])

    out = select(load_results(sweep_dir), datasets, policy_of, config)
    out["fqe_config"] = dataclasses.asdict(config)
    write_json(Path(sweep_dir) / FQE, out)
    return out
