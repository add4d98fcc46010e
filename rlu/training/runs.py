"""Run and sweep folders: the one module that knows their layout and their files, writes them
atomically (``rlu.files``) and reads them back checked, each against its own shape.

A run folder (``rlu train --out RUN``)::

    config.json        the resolved run config, agent config and specs (written once)
    metrics.jsonl      the agent's update metrics, one line every ``log_every`` steps
    eval.jsonl         one line per evaluation: step, episode returns and lengths
    checkpoints/       step_XXXXXXXX.pt: agent state, sampler and RNG states (weights_only)
    result.json        written last, when the run is finished

A sweep folder (``rlu sweep --out SWEEP``)::

    sweep.json         the sweep config
    results.jsonl      one record per finished run (task, agent, config, seed, score, run, and
                       what produced the score: preset, steps, data source, evaluation episodes)
    <task>/<agent>/<config>/seed_<s>/   the run folders (``run`` in a record: relative to SWEEP)
    fqe.json           offline selection by FQE (``rlu report --fqe``; null where FQE has no
                       number, e.g. the rank correlation of one configuration)

Every file is written to a temporary name, synced and renamed, so a kill leaves either the old
file or the new one; the ``.jsonl`` logs are appended line by line and cut back to the last
checkpoint on resume (a torn last line is dropped). Every file is read through ``rlu.files``
against the shape below: a file of the wrong shape is one FormatError naming it, the field and
the fix, before any of its values is used. Rebuilding a finished run as an agent, a policy or
an evaluation is ``rlu.training.restore``'s.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from rlu import files
from rlu.files import AnyJSON, Float, Int, ListOf, MapOf, Optional, Record, Shape, Str
from rlu.training.checkpoints import save_state
from rlu.types import FormatError, RluError

CONFIG = "config.json"
METRICS = "metrics.jsonl"
EVAL = "eval.jsonl"
RESULT = "result.json"
CHECKPOINTS = "checkpoints"
SWEEP_CONFIG = "sweep.json"
RESULTS = "results.jsonl"
FQE = "fqe.json"
REPORT = "report.json"
"""The marker of a report folder (``rlu report --out``): its numbers, with ``"written_by"``
:data:`REPORT_WRITER`; a folder holding another ``report.json`` is not a report of rlu's."""
REPORT_WRITER = "rlu report"

FIX_RUN = "rlu writes it whole (temporary file + rename), so it was damaged or replaced: restore it or train into a new --out"  # noqa: E501
FIX_SWEEP = "rlu writes it whole, so it was damaged or replaced: restore it, or run the sweep again into a new --out"  # noqa: E501

# --- shapes of the files --------------------------------------------------------------------
_DIM = Int(min=0, max=1 << 20)


class _Spec(Shape):
    """An array spec (``rlu.types.ArraySpec.to_json``) or, with ``keyed``, a dict of them."""

    def __init__(self, keyed: bool = False):
        self.keyed = keyed

    _ONE = Record(
        {"shape": ListOf(_DIM, max_len=8), "dtype": Str(max_len=16)},
        {"minimum": Float(), "maximum": Float(), "num_values": Int(min=1, max=1 << 20)},
        extra=False,
    )

    def check(self, value: Any, where: str) -> Any:
        if self.keyed and isinstance(value, Mapping) and not {"shape", "dtype"} <= set(value):
            return MapOf(self._ONE, max_len=1024).check(value, where)
        return self._ONE.check(value, where)

    def describe(self) -> str:
        return "an array spec"


def run_config_shape(train_shape: Shape) -> Record:
    """The shape of a run's config.json; ``train_shape`` is ``rlu.files.shape_of(TrainConfig)``
    (given by rlu.training.train, which owns that config)."""
    return Record(
        {
            "train": train_shape,
            "env_settings": MapOf(AnyJSON(depth=2), max_len=16),
            "agent_config": MapOf(AnyJSON(depth=8), max_len=256),
            "observation_spec": _Spec(keyed=True),
            "action_spec": _Spec(),
            "dataset": Record({"path": Str(), "num_steps": Int(min=0)}),
        }
    )


EVAL_RECORD = Record(
    {
        "step": Int(min=0),
        "returns": ListOf(Float()),
        "lengths": ListOf(Int(min=0)),
        "mean": Float(),
    }
)
METRICS_RECORD = Record({"step": Int(min=0)})
DATA_SOURCE = Record(
    {"source": Str(choices=("release", "generated", "imported", "synthetic", "unknown"))}
)
RESULT_SHAPE = Record(
    {
        "task": Str(),
        "agent": Str(),
        "seed": Int(min=0),
        "steps": Int(min=0),
        "score": Optional(Float()),
        "final_eval": Optional(EVAL_RECORD),
    },
    {
        "pretrain_steps": Int(min=0),
        "env_settings": MapOf(AnyJSON(depth=2), max_len=16),
        "preset": Str(),
        "eval_episodes": Int(min=1),
        "data": DATA_SOURCE,
    },
)
RUN_RECORD = Record(
    {
        "task": Str(),
        "agent": Str(),
        "config": Str(),
        "seed": Int(min=0),
        "score": Optional(Float()),
        "run": Str(),
    },
    {
        "overrides": MapOf(AnyJSON(depth=4), max_len=256),
        "preset": Str(),
        "env_settings": MapOf(AnyJSON(depth=2), max_len=16),
        "returns": Optional(ListOf(Float())),
        "steps": Int(min=0),
        "pretrain_steps": Int(min=0),
        "eval_episodes": Int(min=1),
        "data": DATA_SOURCE,
    },
)
FQE_SHAPE = Record({"selections": ListOf(MapOf(AnyJSON(depth=6)), max_len=100_000)})
RUN_FACTS = Record(
    {
        "train": Record(
            {"task": Str(), "agent": Str(), "seed": Int(min=0)},
            {"overrides": MapOf(AnyJSON(depth=4), max_len=256)},
        ),
        "dataset": Record({"path": Str(), "num_steps": Int(min=0)}),
    }
)
"""What a report reads of a run's config.json (the rest is ``rlu.training.train``'s to check)."""


# --- run folders ----------------------------------------------------------------------------
write_json = files.write_json


def clear_temporary(run: str | os.PathLike) -> None:
    """Remove the temporary files a killed writer left in a run folder (never following links)."""
    files.clear_temporaries(run)


@contextlib.contextmanager
def append_log(path: str | os.PathLike) -> Iterator[Any]:
    """A run log opened for appending (``rlu.files.open_private``): a planted symlink, a hard
    link or anything but a plain file is refused instead of written through."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND
    try:
        fd = files.open_private(path, flags, "run log")
    except OSError as e:
        raise RluError(
            f"{path}: cannot be opened for appending ({e.strerror}); remove it"
        ) from None
    with os.fdopen(fd, "a") as fh:
        yield fh


def read_config(run: str | os.PathLike, train_shape: Shape) -> dict[str, Any]:
    path = Path(run) / CONFIG
    return files.read_json(path, run_config_shape(train_shape), FIX_RUN)


def read_result(run: str | os.PathLike) -> dict[str, Any]:
    return files.read_json(Path(run) / RESULT, RESULT_SHAPE, FIX_RUN)


def config_label(overrides: Mapping[str, Any]) -> str:
    """The label of a hyper-parameter setting, ``"learning_rate=0.001"`` (``"default"``: no
    override); a sweep names its run folders and records by it, a report groups runs by it."""
    return ",".join(f"{k}={overrides[k]}" for k in sorted(overrides)) or "default"


def is_run(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a run folder (``rlu train --out``: it holds config.json)."""
    return (Path(path) / CONFIG).is_file() and not (Path(path) / SWEEP_CONFIG).exists()


def is_sweep(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a sweep folder (``rlu sweep --out``: sweep.json or results.jsonl)."""
    p = Path(path)
    return (p / SWEEP_CONFIG).is_file() or (p / RESULTS).is_file()


def run_record(run: str | os.PathLike) -> dict[str, Any]:
    """A finished run folder as the record a sweep keeps in results.jsonl (task, agent,
    config label, overrides, seed, score, what produced it), from its result.json and
    config.json, plus ``dataset`` (the path it trained on). A run without result.json is still
    training or was stopped: an RluError saying so."""
    run = Path(run)
    if not (run / RESULT).is_file():
        raise RluError(
            f"{run / RESULT} is missing: the run is still training or stopped before its end; "
            f"finish it (rlu train ... --out {run} --resume) or leave it out"
        )
    result = read_result(run)
    facts = files.read_json(run / CONFIG, RUN_FACTS, FIX_RUN)
    train = facts["train"]
    for key in ("task", "agent", "seed"):
        if train[key] != result[key]:
            raise FormatError(
                f"{run / RESULT}: field {key!r} is {result[key]!r} but {run / CONFIG} has "
                f"{train[key]!r}; {FIX_RUN}"
            )
    overrides = dict(train.get("overrides") or {})
    data = dict(result.get("data") or {"source": "unknown"})
    data.setdefault("steps", facts["dataset"]["num_steps"])
    return {
        "task": result["task"],
        "agent": result["agent"],
        "config": config_label(overrides),
        "overrides": overrides,
        "seed": result["seed"],
        "preset": result.get("preset"),
        "steps": result["steps"],
        "pretrain_steps": result.get("pretrain_steps", 0),
        "eval_episodes": result.get("eval_episodes"),
        "data": data,
        "env_settings": result.get("env_settings", {}),
        "score": result["score"],
        "returns": (result.get("final_eval") or {}).get("returns"),
        "run": str(run),
        "dataset": facts["dataset"]["path"],
    }


def learning_curve(run: str | os.PathLike) -> list[dict[str, Any]]:
    """A run's evaluations in order: ``[{"step", "mean", "episodes"}]`` from its eval.jsonl
    (empty when the folder or the file is gone)."""
    path = Path(run) / EVAL
    if not path.is_file():
        return []
    return [
        {"step": r["step"], "mean": r["mean"], "episodes": len(r["returns"])}
        for r in read_log(path)
    ]


def read_log(path: str | os.PathLike, max_step: int | None = None) -> list[dict[str, Any]]:
    """Complete records of a run's metrics.jsonl or eval.jsonl (with ``step <= max_step`` when
    given); a kill can leave a torn last line, which is dropped; a torn line elsewhere, or a
    line of the wrong shape, is a FormatError."""
    shape = EVAL_RECORD if Path(path).name == EVAL else METRICS_RECORD
    records = files.read_jsonl(path, shape, FIX_RUN, allow_nan=True)
    return [r for r in records if max_step is None or r["step"] <= max_step]


def cut_log(path: str | os.PathLike, max_step: int) -> None:
    """Keep the lines of ``path`` logged at or before ``max_step`` (resume from a checkpoint)."""
    import json

    kept = read_log(path, max_step)
    files.write_atomic(path, "".join(json.dumps(r) + "\n" for r in kept))


def checkpoints(run: str | os.PathLike) -> list[Path]:
    """The run's checkpoint files, oldest first (planted links are not checkpoints)."""
    return sorted(p for p in (Path(run) / CHECKPOINTS).glob("step_*.pt") if not p.is_symlink())


def save_checkpoint(run: str | os.PathLike, step: int, state: Mapping[str, Any], keep: int) -> Path:
    """Write ``state`` as ``checkpoints/step_XXXXXXXX.pt`` atomically; keep the newest ``keep``."""
    path = Path(run) / CHECKPOINTS / f"step_{step:08d}.pt"
    save_state(path, state)
    for old in checkpoints(run)[:-keep] if keep > 0 else []:
        old.unlink()
    return path


def find_run(path: str | os.PathLike) -> tuple[Path, Path]:
    """(run folder, checkpoint) of a run folder (its newest checkpoint) or of one checkpoint
    file in it."""
    p = Path(path)
    if p.is_file():
        ckpt, run = p, p.parent.parent
    else:
        run = p
        if not (run / CONFIG).is_file():
            raise RluError(
                f"{run / CONFIG} is missing; {path} is not an rlu run folder or checkpoint "
                "(rlu train --out)"
            )
        found = checkpoints(run)
        if not found:
            raise RluError(f"{run} has no {CHECKPOINTS}/step_*.pt; train it first (rlu train)")
        ckpt = found[-1]
    if not (run / CONFIG).is_file():
        raise RluError(f"{run / CONFIG} is missing; {path} is not an rlu run folder or checkpoint")
    return run, ckpt


# --- sweep folders --------------------------------------------------------------------------
def load_sweep_config(sweep_dir: str | os.PathLike, shape: Shape | None = None) -> dict[str, Any]:
    path = Path(sweep_dir) / SWEEP_CONFIG
    if not path.is_file():
        raise RluError(f"{path} is missing; {sweep_dir} is not a sweep folder (rlu sweep --out)")
    return files.read_json(path, shape or Record({"datasets": MapOf(Str())}), FIX_SWEEP)


def load_results(sweep_dir: str | os.PathLike) -> list[dict[str, Any]]:
    """The sweep's run records, with each ``run`` folder resolved (records store it relative
    to the sweep folder, so a sweep can be moved and reported from anywhere)."""
    path = Path(sweep_dir) / RESULTS
    if not path.exists():
        raise RluError(f"{path} is missing; run the sweep first (rlu sweep ... --out {sweep_dir})")
    fix = "run the sweep again: it rewrites this file from its finished runs"
    records = files.read_jsonl(path, RUN_RECORD, fix, torn="refuse", allow_nan=True)
    root = Path(sweep_dir)
    return [{**r, "run": str(root / r["run"])} for r in records]


def write_results(sweep_dir: str | os.PathLike, records: Sequence[Mapping[str, Any]]) -> None:
    """Write the sweep's records, each ``run`` folder relative to the sweep folder."""
    import json

    root = Path(sweep_dir).resolve()
    lines = []
    for r in records:
        run = Path(r["run"]).resolve()
        rel = os.path.relpath(run, root) if run.is_relative_to(root) else str(run)
        lines.append(json.dumps({**r, "run": rel}) + "\n")
    files.write_atomic(Path(sweep_dir) / RESULTS, "".join(lines))


def read_fqe(sweep_dir: str | os.PathLike) -> dict[str, Any]:
    """A sweep's fqe.json. rlu writes null where FQE has no number; a file from before that
    (NaN, which is not JSON) is read with each NaN as null, never refused as rlu's own."""
    fix = "run rlu report --fqe again"
    path = Path(sweep_dir) / FQE
    value = files.parse_json(files.read_bytes(path, files.MAX_JSON_BYTES, fix), str(path), fix,
                             allow_nan=True)  # fmt: skip
    return files.check_value(FQE_SHAPE, finite_or_none(value), str(path), fix)


def finite_or_none(value: Any) -> Any:
    """``value`` with every NaN or infinity (anywhere in lists and objects) as None: what JSON
    can hold of a number that is not one."""
    import math

    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Mapping):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite_or_none(v) for v in value]
    return value
