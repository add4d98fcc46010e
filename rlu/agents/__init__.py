"""The baselines, one file each, built by name from one registry (``AGENTS``).

Every agent module defines, top to bottom: a frozen ``Config`` dataclass (paper defaults, a
docstring per field), ``PRESETS = {"paper": ..., "small": ...}``, ``GRID`` (the paper's
hyper-parameter grid as data, ``{field: [values]}``), pure loss functions returning
``(loss, metrics)`` and ``Agent(observation_spec, action_spec, config, seed=0, device="cpu")``
meeting ``rlu.types.Agent``: ``batch_spec`` (what its batches are), ``update(batch) ->
dict[str, float]``, ``act(obs, greedy=True, is_first=None)``, ``modules``, ``state_dict()`` /
``load_state_dict()``; its modules, batches and draws live on ``device`` (the pattern:
``rlu.agents.common`` and docs/devices.md). Adding an agent = one file + one line in
``AGENTS``; the contract test (tests/agents/test_contract.py) then runs it. See docs/agents.md.

Config fields of a composed settings dataclass (the Atari agents' ``atari``) are overridden by
dotted path: ``make_config("dqn", True, "small", **{"atari.batch_size": 64})``.

``make_agent`` chooses between the discrete and the continuous variant of ``bc`` / ``bcq`` from
the action spec. Nothing here imports torch until an agent is built.
"""

from __future__ import annotations

import dataclasses
import importlib
import typing
from collections.abc import Mapping
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
    # continuous, beyond the paper
    ("crr", False): "rlu.agents.crr",
    ("iql", False): "rlu.agents.iql",
    ("cql", False): "rlu.agents.cql",
    # continuous, online: distributional MPO, the RWRL data's behaviour agent (rlu generate)
    ("dmpo", False): "rlu.agents.dmpo",
    # discrete (Atari): paper appendix A.2
    ("bc", True): "rlu.agents.bc_discrete",
    ("dqn", True): "rlu.agents.dqn",
    ("iqn", True): "rlu.agents.iqn",
    ("bcq", True): "rlu.agents.bcq_discrete",
    ("rem", True): "rlu.agents.rem",
    ("cql", True): "rlu.agents.cql_discrete",
    # discrete, online: Dopamine's DQN, the Atari data's behaviour agent (rlu generate)
    ("dopamine_dqn", True): "rlu.agents.dqn_online",
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


def _replace(config: Any, path: str, value: Any, agent: str) -> Any:
    """``dataclasses.replace`` along a dotted field path (``atari.batch_size``)."""
    head, _, rest = path.partition(".")
    fields = {f.name for f in dataclasses.fields(config)}
    if head not in fields:
        nested = [
            f"{f}.{head}"
            for f in sorted(fields)
            if dataclasses.is_dataclass(getattr(config, f))
            and head in {g.name for g in dataclasses.fields(getattr(config, f))}
        ]
        hint = f"; did you mean {' or '.join(nested)}?" if nested else ""
        raise RluError(
            f"agent {agent!r} config has no field {path!r}{hint} fields: "
            f"{', '.join(sorted(fields))}"
        )
    current = getattr(config, head)
    if rest:
        if not dataclasses.is_dataclass(current):
            raise RluError(f"agent {agent!r} config field {head!r} has no sub-fields ({path!r})")
        value = _replace(current, rest, value, agent)
    elif dataclasses.is_dataclass(current) and isinstance(value, Mapping):
        value = config_from_json(type(current), {**dataclasses.asdict(current), **value})
    elif isinstance(current, tuple) and isinstance(value, list):
        value = tuple(value)  # JSON and the CLI give lists where configs hold tuples
    return dataclasses.replace(config, **{head: value})


def make_config(name: str, discrete: bool, preset: str = "small", **overrides: Any) -> Any:
    """The preset's config with ``overrides`` applied (dotted paths reach composed settings;
    unknown fields are an error)."""
    module = agent_module(name, discrete)
    try:
        config = module.PRESETS[preset]
    except KeyError:
        raise RluError(
            f"agent {name!r} has no preset {preset!r}; presets: {', '.join(module.PRESETS)}"
        ) from None
    for path, value in overrides.items():
        config = _replace(config, path, value, name)
    return config


def config_from_json(cls: type, data: Mapping[str, Any]) -> Any:
    """Rebuild a (possibly nested) frozen config dataclass from its JSON form (lists back to
    tuples, dicts back to the composed dataclasses); unknown keys are an error."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise RluError(
            f"{cls.__name__} has no field(s) {', '.join(unknown)}; the run was written by "
            "another version of this agent"
        )
    values = {}
    for key, value in data.items():
        kind = hints[key]
        if dataclasses.is_dataclass(kind) and isinstance(value, Mapping):
            value = config_from_json(kind, value)
        elif isinstance(value, list):
            value = tuple(value)
        values[key] = value
    return cls(**values)


def make_agent(
    name: str,
    observation_spec: ObservationSpec,
    action_spec: ActionSpec,
    preset: str = "small",
    seed: int = 0,
    config: Any = None,
    device: Any = "cpu",
    **overrides: Any,
) -> Any:
    """Build agent ``name`` for the given specs (``config`` wins over ``preset``/``overrides``)
    on ``device`` ('cpu', 'cuda', 'cuda:N', 'auto'; docs/devices.md)."""
    discrete = isinstance(action_spec, DiscreteSpec)
    module = agent_module(name, discrete)
    if config is None:
        config = make_config(name, discrete, preset, **overrides)
    return module.Agent(observation_spec, action_spec, config, seed=seed, device=device)
