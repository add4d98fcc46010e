"""How a training run is run, in one frozen value, and its config files.

:class:`RunSettings` holds everything about a run that is not *what* it trains (task, agent,
dataset, seed, agent overrides): preset, budget, evaluation, logging, checkpoints, the env
factory, threads and the runtime (``rlu.devices.Runtime``). ``rlu.training.prepare.TrainConfig``
composes it; ``rlu.training.sweep.SweepConfig`` holds one as the template of every run; the quick
start builds one. A new training option is one field here: its flag, type check, range check and
help text come from the field (``rlu.commands._options``: the command line's side), its check in
Python and in a run's config.json from the same field (``rlu.files.Checked``,
``rlu.files.shape_of``). Config files (:func:`read_config_file`, :func:`config_from_file`) are
read here, below the commands, because the library reads them too.

Standard library only.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from typing import Any

from rlu.devices import Runtime
from rlu.files import MAX_DEPTH, MAX_STEPS, STEPS, Checked, bounds
from rlu.types import RluError

EVAL_EVERY_MIN = 10_000
"""Fewest learner steps between two periodic evaluations when ``eval_every`` is left unset."""


@dataclass(frozen=True)
class RunSettings(Checked):
    """How one training run is run (see the module docstring)."""

    preset: str = "small"
    """Agent preset: small (minutes on a laptop CPU; the default for a first run) or paper (the
    paper's settings and budget, e.g. 2M steps on Atari); numbers beside the paper's need paper."""
    steps: int | None = field(default=None, metadata=STEPS)
    """Learner steps (default: the preset's num_steps)."""
    eval_every: int | None = field(default=None, metadata=bounds(min=-1, max=MAX_STEPS))
    """Learner steps between evaluations in the env (default: every max(10,000, steps / 10) and
    at the end; 0: only at the end; -1: never)."""
    eval_at_start: bool = False
    """Also evaluate the untrained agent before its first update (step 0 of the learning
    curve in eval.jsonl)."""
    eval_episodes: int = field(default=5, metadata=bounds(min=1, max=100_000, metavar="N"))
    """Env episodes per evaluation."""
    eval_envs: int = field(default=4, metadata=bounds(min=1, max=1024, metavar="N"))
    """Envs stepped in lockstep during an evaluation (the returns do not depend on it)."""
    eval_max_steps: int | None = field(
        default=None, metadata=bounds(min=1, max=MAX_STEPS, metavar="N")
    )
    """Cap on an evaluation episode's steps on top of the env's own limit (default: the env's)."""
    log_every: int = field(default=100, metadata=bounds(min=1, max=MAX_STEPS, metavar="N"))
    """Learner steps between lines of metrics.jsonl."""
    checkpoint_every: int = field(default=1000, metadata=bounds(min=1, max=MAX_STEPS, metavar="N"))
    """Learner steps between checkpoints (one is always written at the end)."""
    keep_checkpoints: int = field(default=2, metadata=bounds(min=1, max=1000, metavar="N"))
    """Checkpoints kept on disk (the newest)."""
    env: str | None = field(default=None, metadata=bounds(metavar="MODULE:FUNCTION"))
    """Env factory 'module:function' taking (task_id, seed=...), imported because you typed it
    (default: rlu.envs.make_env); a run folder's config.json never names one that is imported."""
    challenge: str | None = field(default=None, metadata=bounds(choices=("none", "easy")))
    """RWRL: the challenge to evaluate under (default: the one the data was recorded under)."""
    torch_threads: int = field(
        default=1, metadata=bounds(min=1, max=1024, flag="--threads", metavar="N")
    )
    """torch threads per run (1: faster than one per core for these batch sizes on a shared
    machine; bench/README.md)."""
    sampler: str = field(default="auto", metadata=bounds(choices=("auto", "uniform", "stream")))
    """Where batches come from: uniform (exact uniform draws from the memory-mapped dataset),
    stream (rlu.data.StreamSampler: the files read in order into a bounded buffer, every sample
    drawn --stream-reuse times a pass: for runs larger than the page cache and mixtures; docs/
    data.md), or auto: uniform for one dataset, stream for several."""
    stream_memory: int = field(default=2048, metadata=bounds(min=16, max=1 << 20, metavar="MB"))
    """The stream sampler's buffer of decoded frames and steps, in MB (its batches depend on
    it: a resumed run keeps it)."""
    stream_reuse: int = field(default=8, metadata=bounds(min=1, max=10_000, metavar="N"))
    """Draws of each sample per pass of the stream sampler."""
    runtime: Runtime = field(default_factory=Runtime)
    """Device, precision, TF32, compile and data path: how the run computes, which may change
    between its sessions (rlu.devices.Runtime)."""

    def eval_period(self, total: int) -> int:
        """Learner steps between evaluations of a run of ``total`` steps (``total`` when it
        evaluates only at the end; 0 when it never does)."""
        if self.eval_every == -1:
            return 0
        if self.eval_every is None:
            return min(total, max(EVAL_EVERY_MIN, total // 10))
        return self.eval_every or total


# --- type hints -----------------------------------------------------------------------------
def scalar_hint(hint: Any) -> tuple[Any, bool]:
    """(the non-None type of a hint, whether None is allowed): how a field's declared type is read
    here and by the command line's options (``rlu.commands._options``)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        rest = [a for a in typing.get_args(hint) if a is not type(None)]
        return (rest[0] if len(rest) == 1 else str), True
    return hint, False


# --- config files ---------------------------------------------------------------------------
MAX_CONFIG_BYTES = 1 << 20
"""Largest run config file rlu reads (a run's config.json is a few kB)."""


def _optional_shape(cls: type) -> Any:
    """``rlu.files.shape_of(cls)`` with every field optional (a config file may give some)."""
    from rlu.files import Record, shape_of

    shape = shape_of(cls)
    fields = {**shape.required, **shape.optional}
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        hint, _ = scalar_hint(hints[f.name])
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            fields[f.name] = _optional_shape(hint)
    return Record({}, fields, extra=False)


def read_config_file(path: str, cls: type) -> dict[str, Any]:
    """A config file (JSON, or YAML by its .yaml / .yml name) holding some fields of dataclass
    ``cls`` (nested dataclasses as objects), checked against their shapes; a run folder's
    config.json (``{"train": {...}, ...}``) gives its ``train`` object. YAML is read with
    PyYAML's safe loader, after a pass over its events that refuses anchors / aliases (their
    expansion is unbounded) and nesting deeper than ``rlu.files.MAX_DEPTH``; the file is at most
    ``MAX_CONFIG_BYTES``, so reading it is bounded in time and memory too."""
    from pathlib import Path

    from rlu.files import check_value, parse_json, read_bytes
    from rlu.system import install_hint
    from rlu.types import FormatError

    fix = "write it as JSON or YAML with the fields of `rlu train --help`"
    raw = read_bytes(path, MAX_CONFIG_BYTES, fix)
    if Path(path).suffix.lower() in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise FormatError(
                f"{path}: reading YAML needs PyYAML: {install_hint('agents')}"
            ) from None
        try:
            depth = 0
            for event in yaml.parse(raw, Loader=yaml.SafeLoader):
                if isinstance(event, yaml.AliasEvent):
                    raise FormatError(f"{path}: YAML aliases (*name) are not read; {fix}")
                if isinstance(event, yaml.CollectionStartEvent):
                    depth += 1
                    if depth > MAX_DEPTH:
                        raise FormatError(
                            f"{path}: YAML nested deeper than {MAX_DEPTH} levels (line "
                            f"{event.start_mark.line + 1}); a run config nests 3; {fix}"
                        )
                elif isinstance(event, yaml.CollectionEndEvent):
                    depth -= 1
            data = yaml.safe_load(raw)
        except yaml.YAMLError as e:
            why = " ".join(str(e).split())[:200]
            raise FormatError(f"{path}: not valid YAML ({why}); {fix}") from None
        except RecursionError:
            raise FormatError(f"{path}: YAML nested too deep; {fix}") from None
    else:
        data = parse_json(raw, str(path), fix)
    if isinstance(data, dict) and "train" in data and "agent_config" in data:
        data = data["train"]  # a run folder's config.json
    return check_value(_optional_shape(cls), data, str(path), fix)


def config_from_file(cls: type, path: str, given: dict[str, Any] | None = None) -> Any:
    """The ``cls`` value of config file ``path`` (:func:`read_config_file`): nested objects
    become their dataclasses, lists tuples where the field is a tuple; ``given`` fills or
    replaces top-level fields (what code names itself). A module path the file names (a dotted
    agent, an env factory) is refused unless ``given`` names it too: names in files are never
    imported (``given`` replaces that field). A required field that neither holds is an error
    naming the file and the field."""
    given = dict(given or {})
    data = read_config_file(path, cls)
    for key in ("agent", "agents"):
        names = data.get(key)
        names = [names] if isinstance(names, str) else list(names or ())
        dotted = [n for n in names if "." in n]
        if dotted and key not in given:
            raise RluError(
                f"{path}: field {key!r} names the agent module {dotted[0]!r}, and a module named "
                f"in a file is never imported; if you trust it, pass {key}=... yourself (or type "
                f"--agent {dotted[0]})"
            )
    env = data.get("run", {}).get("env")
    if env is not None and "run" not in given:
        raise RluError(
            f"{path}: field 'run.env' names the env factory {env!r}, and a module named in a "
            f"file is never imported; if you trust it, pass run=RunSettings(env={env!r}, ...) "
            f"yourself (or type --env {env})"
        )
    data.update(given)
    try:
        return _build(cls, data)
    except TypeError as e:
        missing = [
            f.name
            for f in dataclasses.fields(cls)
            if f.name not in data
            and f.default is dataclasses.MISSING
            and f.default_factory is dataclasses.MISSING
        ]
        if missing:
            raise RluError(
                f"{path}: field {missing[0]!r} is missing; add it to the file or pass it "
                f"({missing[0]}=...)"
            ) from None
        raise RluError(f"{path}: {e}") from None


def _build(cls: type, data: dict[str, Any]) -> Any:
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        hint, _ = scalar_hint(hints[f.name])
        if isinstance(hint, type) and dataclasses.is_dataclass(hint) and isinstance(value, dict):
            value = _build(hint, value)
        elif typing.get_origin(hint) is tuple and isinstance(value, list):
            value = tuple(value)
        values[f.name] = value
    return cls(**values)
