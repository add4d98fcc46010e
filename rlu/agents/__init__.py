"""The baselines, one file each, built by name from one registry (``AGENTS``).

Every agent module defines, top to bottom: a frozen ``Config`` dataclass (paper defaults, a
docstring per field), ``PRESETS = {"paper": ..., "small": ...}``, ``GRID`` (the paper's
hyper-parameter grid as data, ``{field: [values]}``), pure loss functions returning
``(loss, metrics)`` and ``Agent(observation_spec, action_spec, config, seed=0, device="cpu")``
meeting ``rlu.types.Agent``: ``batch_spec`` (what its batches are), ``update(batch) ->
dict[str, float]``, ``act(obs, greedy=True, is_first=None, reward=None)``, ``modules``,
``state_dict()`` / ``load_state_dict()``; its modules, batches and draws live on ``device``
(the pattern: ``rlu.agents.common`` and docs/devices.md). Adding an agent = one file + one line in
``AGENTS``; the contract test (tests/agents/test_contract.py) then runs it. See docs/agents.md.

Config fields of a composed settings dataclass (the Atari agents' ``atari``) are overridden by
dotted path: ``make_config("dqn", True, "small", **{"atari.batch_size": 64})``.

``make_agent`` chooses between the discrete and the continuous variant of ``bc`` / ``bcq`` from
the action spec (``dt``'s one module serves both, with its settings of either kind). Nothing
here imports torch until an agent is built.
"""

from __future__ import annotations

import dataclasses
import importlib
import typing
from collections.abc import Mapping
from typing import Any

from rlu.types import ActionSpec, ConfigError, DiscreteSpec, ObservationSpec, RluError

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
    ("td3bc", False): "rlu.agents.td3bc",
    ("rebrac", False): "rlu.agents.rebrac",
    # continuous, online: distributional MPO, the RWRL data's behaviour agent (rlu generate)
    ("dmpo", False): "rlu.agents.dmpo",
    # both action types, beyond the paper: Decision Transformer (one module, settings by action)
    ("dt", False): "rlu.agents.dt",
    # discrete (Atari): paper appendix A.2
    ("bc", True): "rlu.agents.bc_discrete",
    ("dqn", True): "rlu.agents.dqn",
    ("iqn", True): "rlu.agents.iqn",
    ("bcq", True): "rlu.agents.bcq_discrete",
    ("rem", True): "rlu.agents.rem",
    ("cql", True): "rlu.agents.cql_discrete",
    # discrete, online: Dopamine's DQN, the Atari data's behaviour agent (rlu generate)
    ("dopamine_dqn", True): "rlu.agents.dqn_online",
    # discrete, beyond the paper: Decision Transformer (the module above, its `atari` settings)
    ("dt", True): "rlu.agents.dt",
    # discrete, beyond the paper: recurrent Q-learning on sequences (R2D2, DMLab's recorder)
    ("r2d2", True): "rlu.agents.r2d2",
}

CONTINUOUS_AGENTS: tuple[str, ...] = tuple(n for n, d in AGENTS if not d)
DISCRETE_AGENTS: tuple[str, ...] = tuple(n for n, d in AGENTS if d)


_TRUSTED: dict[str, Any] = {}
"""Agent modules outside ``AGENTS`` that code or the command line named (:func:`trust_agent`)."""
_CONVENTION = ("Config", "Agent", "PRESETS", "GRID")


def trust_agent(path: str) -> Any:
    """Import the agent module at dotted ``path`` (``mypkg.my_agent``, following the agent-module
    convention: ``Config``, ``Agent``, ``PRESETS``, ``GRID``) and register it under ``path`` for
    this process. Only code and the command line call this: a name read from a file (a run's
    config.json, a policy's JSON) is looked up (:func:`agent_module`), never imported."""
    if path in _TRUSTED:
        return _TRUSTED[path]
    if not all(part.isidentifier() for part in path.split(".")):
        raise RluError(f"agent module {path!r} is not a dotted module path (mypkg.my_agent)")
    try:
        module = importlib.import_module(path)
    except ImportError as e:
        raise RluError(f"agent module {path!r} cannot be imported: {e}") from None
    missing = [name for name in _CONVENTION if not hasattr(module, name)]
    if missing:
        raise RluError(
            f"agent module {path!r} has no {', '.join(missing)}; an agent module defines "
            f"{', '.join(_CONVENTION)} (docs/agents.md)"
        )
    _TRUSTED[path] = module
    return module


def trusted_agents() -> tuple[str, ...]:
    """The agent modules registered in this process by :func:`trust_agent` (a process pool
    registers them again in its workers)."""
    return tuple(_TRUSTED)


def agent_module(name: str, discrete: bool) -> Any:
    """The module of agent ``name``: one of ``AGENTS`` or a module registered with
    :func:`trust_agent`; nothing is imported by a name alone."""
    if name in _TRUSTED:
        return _TRUSTED[name]
    try:
        path = AGENTS[(name, discrete)]
    except KeyError:
        names = sorted({n for n, d in AGENTS if d == discrete})
        kind = "discrete" if discrete else "continuous"
        if "." in name:
            raise RluError(
                f"agent {name!r} is not one of rlu's {kind} agents, and a module path named in a "
                f"file is never imported; if you trust that module, name it yourself: --agent "
                f"{name} on the command line, or rlu.agents.trust_agent({name!r})"
            ) from None
        raise RluError(
            f"unknown {kind} agent {name!r}; {kind} agents are: {', '.join(names) or 'none yet'}"
        ) from None
    return importlib.import_module(path)


def _replace(config: Any, path: str, value: Any, agent: str, full: str = "") -> Any:
    """``dataclasses.replace`` along a dotted field path (``atari.batch_size``; ``full``: the
    whole path, for messages)."""
    full = full or path
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
        raise ConfigError(
            f"agent {agent!r} config has no field {path!r}{hint} fields: "
            f"{', '.join(sorted(fields))}"
        )
    current = getattr(config, head)
    if rest:
        if not dataclasses.is_dataclass(current):
            raise ConfigError(f"agent {agent!r} config field {head!r} has no sub-fields ({path!r})")
        value = _replace(current, rest, value, agent, full)
    elif (dataclasses.is_dataclass(current) and not isinstance(current, type)
          and isinstance(value, Mapping)):  # fmt: skip
        value = config_from_json(type(current), {**dataclasses.asdict(current), **value})
    else:
        value = _checked(type(config), head, value, agent, full)
    try:
        return dataclasses.replace(config, **{head: value})
    except ConfigError as e:  # a check of the whole config (its own __post_init__)
        from rlu.files import _short

        raise ConfigError(f"agent {agent!r}: {e} (override {full}={_short(value)})") from None


def _checked(cls: type, name: str, value: Any, agent: str, full: str) -> Any:
    """An override's value, checked against the field's type and bounds (lists as tuples): a
    string for a number, a float for a count, a list of strings for layer widths, a value out
    of range are errors naming the field, the value, the bound and the override (``full``)."""
    from rlu.files import Bad, _short, field_shape

    if isinstance(value, tuple):
        value = list(value)
    shape = field_shape(cls, name)
    try:
        return shape.check(value, name)
    except Bad as e:
        raise ConfigError(
            f"agent {agent!r} config field {e.where!r} {e.what} (override {full}={_short(value)})"
        ) from None


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
        if isinstance(kind, type) and dataclasses.is_dataclass(kind) and isinstance(value, Mapping):
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
    elif dataclasses.is_dataclass(config) and not isinstance(config, type):
        from rlu.files import check_fields

        check_fields(config)  # a config built past its checks (object.__setattr__, a copy)
    return module.Agent(observation_spec, action_spec, config, seed=seed, device=device)


def paper_steps(name: str, discrete: bool) -> int | None:
    """The learner budget of agent ``name``'s paper preset: what a run must reach for its score
    to stand beside the paper's (None: no such agent, no paper preset, or torch missing, so
    the agent module cannot be read). Continuous configs hold ``num_steps``; discrete ones
    their shared Atari settings' (``config.atari.num_steps``)."""
    try:
        config = agent_module(name, discrete).PRESETS.get("paper")
    except (RluError, ImportError):
        return None
    if config is None:
        return None
    return int(config.atari.num_steps if discrete else config.num_steps)
