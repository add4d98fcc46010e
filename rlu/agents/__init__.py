"""The ten baselines of the paper, one file each, built by name.

Every agent module defines, top to bottom: a frozen ``<Algo>Config`` dataclass (paper defaults),
``PRESETS = {"paper": ..., "small": ...}``, ``GRID`` (the paper's hyper-parameter grid as data,
``{field: [values]}``), pure loss functions returning ``(loss, metrics)`` and ``<Algo>Agent`` with
``update(batch) -> dict[str, float]``, ``act(obs, greedy=True)``, ``state_dict()`` /
``load_state_dict()`` and the attributes the training loop reads:
``batch_kind`` ("transition" or "sequence"), ``n_step`` and ``sequence_length``.

``make_agent`` chooses between the discrete and the continuous variant of ``bc`` / ``bcq`` from
the action spec. Nothing here imports torch until an agent is built.
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Any

from rlu.types import ActionSpec, DiscreteSpec, ObservationSpec, RluError

# (name, discrete) -> module path. The module holds Config, Agent, PRESETS and GRID.
AGENTS: dict[tuple[str, bool], str] = {
    # continuous (control suite, locomotion, RWRL): paper appendix A.1
    ("bc", False): "rlu.agents.bc",
    ("d4pg", False): "rlu.agents.d4pg",
    ("bcq", False): "rlu.agents.bcq",
    ("brac", False): "rlu.agents.brac",
    ("rabm", False): "rlu.agents.rabm",
    # discrete (Atari): paper appendix A.2
    ("bc", True): "rlu.agents.bc_discrete",
    ("dqn", True): "rlu.agents.dqn",
    ("iqn", True): "rlu.agents.iqn",
    ("bcq", True): "rlu.agents.bcq_discrete",
    ("rem", True): "rlu.agents.rem",
}

CONTINUOUS_AGENTS: tuple[str, ...] = tuple(n for n, d in AGENTS if not d)
DISCRETE_AGENTS: tuple[str, ...] = tuple(n for n, d in AGENTS if d)


def agent_module(name: str, discrete: bool) -> Any:
    """The module of agent ``name``; a dotted module path (``mypkg.my_agent``) is imported as is."""
    if "." in name:
        try:
            return importlib.import_module(name)
        except ImportError as e:
            raise RluError(f"agent module {name!r} cannot be imported: {e}") from None
    try:
        path = AGENTS[(name, discrete)]
    except KeyError:
        names = sorted({n for n, d in AGENTS if d == discrete})
        kind = "discrete" if discrete else "continuous"
        raise RluError(
            f"unknown {kind} agent {name!r}; {kind} agents are: {', '.join(names) or 'none yet'}"
        ) from None
    return importlib.import_module(path)


def make_config(name: str, discrete: bool, preset: str = "small", **overrides: Any) -> Any:
    """The preset's config with ``overrides`` applied (unknown fields are an error)."""
    module = agent_module(name, discrete)
    try:
        config = module.PRESETS[preset]
    except KeyError:
        raise RluError(
            f"agent {name!r} has no preset {preset!r}; presets: {', '.join(module.PRESETS)}"
        ) from None
    fields = {f.name for f in dataclasses.fields(config)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise RluError(
            f"agent {name!r} config has no field(s) {', '.join(unknown)}; fields: "
            f"{', '.join(sorted(fields))}"
        )
    # JSON and the CLI give lists where configs hold tuples (layer sizes)
    values = {
        k: tuple(v) if isinstance(getattr(config, k), tuple) and isinstance(v, list) else v
        for k, v in overrides.items()
    }
    return dataclasses.replace(config, **values)


def make_agent(
    name: str,
    observation_spec: ObservationSpec,
    action_spec: ActionSpec,
    preset: str = "small",
    seed: int = 0,
    config: Any = None,
    **overrides: Any,
) -> Any:
    """Build agent ``name`` for the given specs (``config`` wins over ``preset``/``overrides``)."""
    discrete = isinstance(action_spec, DiscreteSpec)
    module = agent_module(name, discrete)
    if config is None:
        config = make_config(name, discrete, preset, **overrides)
    return module.Agent(observation_spec, action_spec, config, seed=seed)
