"""A finished run, rebuilt from its folder: its agent, its greedy policy, its evaluation,
offline selection by FQE over a sweep of such runs.

Everything here reads files (``rlu.training.runs``: each checked against its shape), so every name
those files hold is looked up, never imported: the agent in the registry (``rlu.agents``; a module
path must have been trusted by code or on the command line: ``rlu evaluate RUN --agent
MODULE``), the task in ``rlu.tasks``. An env factory recorded in a run's config.json is not used
unless the caller names it again (``--env``). A config that does not build its agent, or a
checkpoint of another agent or of other shapes, is a FormatError naming the file.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rlu.training import runs
from rlu.types import (
    ArraySpec,
    DiscreteSpec,
    FormatError,
    RluError,
    observation_spec_from_json,
)

_BUILD_ERRORS = (RuntimeError, ValueError, TypeError, KeyError, OverflowError, MemoryError)


def read_run(path: str | os.PathLike) -> tuple[dict[str, Any], Path, Path]:
    """(resolved config, run folder, checkpoint) of a run folder (its newest checkpoint) or of
    one checkpoint file in it, the config checked against its shape."""
    from rlu.training.prepare import TrainConfig

    run, ckpt = runs.find_run(path)
    return runs.read_config(run, TrainConfig.shape()), run, ckpt


def build_agent(resolved: Mapping[str, Any], device: Any = "cpu", what: str = "config.json") -> Any:
    """The agent a run's resolved config describes, freshly initialised (config, specs, seed)
    on ``device`` (any device: the one the run trained on does not matter)."""
    from rlu.agents import agent_module, config_from_json
    from rlu.files import check_value, shape_of

    fix = "restore the run's config.json, or train into a new --out"
    train_cfg = resolved["train"]
    try:
        obs_spec = observation_spec_from_json(resolved["observation_spec"])
        action_spec = ArraySpec.from_json(resolved["action_spec"])
    except (ValueError, TypeError, KeyError) as e:
        raise FormatError(
            f"{what}: field 'observation_spec' or 'action_spec': {e}; {fix}"
        ) from None
    module = agent_module(train_cfg["agent"], isinstance(action_spec, DiscreteSpec))
    data = check_value(shape_of(module.Config), resolved["agent_config"], what, fix)
    try:
        config = config_from_json(module.Config, data)
        return module.Agent(
            obs_spec, action_spec, config, seed=int(train_cfg["seed"]), device=device
        )
    except RluError:
        raise
    except _BUILD_ERRORS as e:
        why = (str(e).splitlines() or [type(e).__name__])[0][:200]
        raise FormatError(
            f"{what}: its agent_config does not build a {train_cfg['agent']} agent ({why}); {fix}"
        ) from None


def load_agent(path: str | os.PathLike, device: Any = "cpu") -> tuple[Any, dict[str, Any]]:
    """(agent restored on ``device`` from a run's newest checkpoint or a given checkpoint,
    resolved config)."""
    from rlu.training.checkpoints import load_state

    resolved, run, ckpt = read_run(path)
    agent = build_agent(resolved, device, str(run / runs.CONFIG))
    state = load_state(ckpt, ("agent",))
    try:
        agent.load_state_dict(state["agent"])
    except (RuntimeError, KeyError, ValueError, TypeError, AttributeError) as e:
        why = (str(e).splitlines() or [type(e).__name__])[0][:200]
        raise FormatError(
            f"{ckpt}: its agent state does not fit the agent of {run / runs.CONFIG} ({why}); "
            "use a checkpoint of this run"
        ) from None
    return agent, resolved


def load_policy(path: str | os.PathLike, device: Any = "cpu") -> tuple[Any, dict[str, Any]]:
    """(greedy policy of a run's newest checkpoint or of a given checkpoint, acting on
    ``device``, resolved config)."""
    from rlu.training.loop import greedy_policy

    agent, resolved = load_agent(path, device)
    return greedy_policy(agent), resolved


def evaluate_run(
    path: str | os.PathLike,
    episodes: int = 10,
    seed: int = 0,
    num_envs: int = 4,
    env: str | None = None,
    max_steps: int | None = None,
    challenge: str | None = None,
    device: Any = "cpu",
    observer: Any = None,
    render: Mapping[str, Any] | None = None,
) -> Any:
    """Roll out the greedy policy of a run folder's newest checkpoint (or a given checkpoint) in
    the env the run evaluated in (an RWRL run: its data's challenge, unless ``challenge``),
    acting on ``device``. ``env``: an env factory 'module:function' the caller trusts (a run
    trained with one needs it named again: the one in its config.json is not imported).
    ``observer`` watches the episodes (``rlu.evaluation.rollout.EpisodeObserver``: a video
    ``Recorder``, progress); ``render`` adds the env's render settings (``render_mode``,
    ``render_size``) for one that films them."""
    from rlu.evaluation.rollout import evaluate, task_env_factory
    from rlu.tasks import check_challenge

    resolved, run, _ = read_run(path)
    train_cfg = resolved["train"]
    recorded_env = train_cfg["run"]["env"]
    if env is None and recorded_env is not None:
        raise RluError(
            f"{run / runs.CONFIG}: field 'train.run.env' names the env factory {recorded_env!r}, "
            "and a module named in a file is never imported; if you trust it, name it "
            f"yourself: --env {recorded_env}"
        )
    settings = dict(resolved["env_settings"])
    if challenge is not None:
        if "challenge" not in settings:
            raise RluError(f"--challenge applies to rwrl runs only; {path} is {train_cfg['task']}")
        keys = set(resolved["observation_spec"])
        check_challenge(train_cfg["task"], challenge, keys, settings["challenge"], str(path))
        settings["challenge"] = challenge
    policy, _ = load_policy(path, device)
    env_fn = task_env_factory(train_cfg["task"], env, **settings, **(render or {}))
    return evaluate(policy, env_fn, episodes, seed, num_envs, max_steps, observer)


def fqe_selection(
    sweep_dir: str | os.PathLike, config: Any = None, device: Any = "cpu", quiet: bool = False
) -> dict[str, Any]:
    """Offline policy selection by FQE over a finished sweep (see
    ``rlu.evaluation.fqe.fqe_selection``), policies and FQE on ``device``; writes and returns
    ``SWEEP_DIR/fqe.json``."""
    from rlu.evaluation.fqe import FQEConfig
    from rlu.evaluation.fqe import fqe_selection as select

    config = config or FQEConfig()
    datasets = runs.load_sweep_config(sweep_dir)["datasets"]

    def policy_of(run: str) -> tuple[Any, Any]:
        policy, resolved = load_policy(run, device)
        return policy, ArraySpec.from_json(resolved["action_spec"])

    out = select(runs.load_results(sweep_dir), datasets, policy_of, config, device, quiet)
    out["fqe_config"] = dataclasses.asdict(config)
    # a number FQE does not have (the rank correlation of one configuration, an estimate that
    # diverged) is null: JSON has no NaN, and the report reads this file back
    out = runs.finite_or_none(out)
    runs.write_json(Path(sweep_dir) / runs.FQE, out)
    return out
