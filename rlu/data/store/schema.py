"""What a stored dataset holds: its schema, its files, and a segment as the store's columns.

Layout of a dataset directory::

    manifest.json                 schema, counts, per-file sha256 and size, provenance
    steps/<column>.bin            one raw little-endian array per step column
    steps/observation/<key>.bin   (nested keys become folders)
    steps/observation/<key>.zlib  compressed image columns: one zlib stream per frame,
    steps/observation/<key>.offsets.bin   with int64 offsets (n + 1) into the stream file
    segments/<field>.bin          per-segment index (start, length, frame_start) and metadata
    policies/...                  attachments (optional): files that are not columns, e.g. the
                                  behaviour policies ``rlu generate`` keeps (rlu.generate.policies)
    source/...                    attachments: what an import kept of a D4RL, d3rlpy or Minari
                                  file that the columns do not hold (rlu.data.roundtrip)

Step columns: ``action``, ``reward``, ``discount``, ``is_first``, ``is_last``, ``is_terminal``
and one per observation key. With ``frame_stack > 1`` (Atari) the single observation column holds
frames, not steps: segment s owns frames
``frame_start[s] .. frame_start[s] + (frame_stack - 1) + length[s]``, the first
``frame_stack - 1`` being the frames before its step 0 (zeros at an episode start).

A manifest is input like any other: :meth:`Schema.from_json` accepts only what the writer can
produce (known dtypes, bounded shapes, observation keys that stay inside ``steps/``) and names the
field it refuses.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rlu.domains import DOMAINS
from rlu.segments import METADATA_FIELDS, Segment
from rlu.types import (
    ActionSpec,
    ArraySpec,
    BoundedSpec,
    DiscreteSpec,
    FormatError,
    ObservationSpec,
    SpecError,
    observation_spec_to_json,
)

FORMAT = "rlu-episodes"
"""The ``format`` field of every rlu manifest."""
FORMAT_VERSION = 1
"""The store format's version; a manifest of another version is refused."""
MANIFEST = "manifest.json"
"""The manifest's file name in a dataset folder."""
FLAG_COLUMNS = ("is_first", "is_last", "is_terminal")
"""The boolean step columns: episode starts, ends, and terminal ends (discount 0)."""
ENCODINGS = ("raw", "zlib")
"""How a column's bytes are stored: ``raw`` (a flat memory-mapped file) or ``zlib`` (one deflated
stream per image frame)."""
SEGMENT_INDEX = ("start", "length", "frame_start")
ATTACHMENT_DIRS = ("policies", "source")
"""Top-level folders that may hold attachments: files listed in the manifest (sha256 and size,
checked like the columns) besides the schema's own files."""


def is_attachment(rel: str) -> bool:
    """Whether manifest path ``rel`` names an attachment (a file under ``ATTACHMENT_DIRS``)."""
    head, sep, rest = rel.partition("/")
    return bool(sep) and head in ATTACHMENT_DIRS and bool(rest)


DTYPES = (
    "bool",
    "uint8",
    "int8",
    "uint16",
    "int16",
    "uint32",
    "int32",
    "uint64",
    "int64",
    "float16",
    "float32",
    "float64",
)
"""The numeric dtypes a column may have (never ``object``: nothing in a dataset is a pickle)."""
MAX_FRAME_STACK = 64
MAX_RANK = 8
MAX_STEP_ELEMENTS = 1 << 28
"""Elements of one step of one column (a 4096x4096x16 image); more is damage, not data."""
_KEY_PART = re.compile(r"[A-Za-z0-9_.+-]+")


class FieldError(FormatError):
    """A manifest field with a value the store cannot hold; the reader adds the file's name."""

    def __init__(self, field: str, why: str):
        self.field, self.why = field, why
        super().__init__(f"field {field!r} {why}")


@dataclass(frozen=True)
class Schema:
    """What one stored step holds.

    ``observation`` is the per-step stored spec: a dict keyed like the TaskSpec, or one array; with
    ``frame_stack > 1`` the array is a single frame (Atari: (84, 84)) and the view stacks
    ``frame_stack`` of them on the last axis.
    """

    observation: ObservationSpec
    action: ActionSpec
    frame_stack: int = 1
    image_encoding: str = "raw"
    """'raw' or 'zlib' (per-frame zlib streams, decoded at sample time) for uint8 columns of
    rank >= 2."""
    task_id: str | None = None

    def __post_init__(self) -> None:
        if self.image_encoding not in ENCODINGS:
            raise SpecError(
                f"schema field image_encoding={self.image_encoding!r}; use one of {ENCODINGS}"
            )
        if self.frame_stack < 1:
            raise SpecError(f"schema field frame_stack={self.frame_stack}; use 1 or more")
        if self.frame_stack > 1 and not isinstance(self.observation, ArraySpec):
            raise SpecError("frame_stack > 1 needs a single-array observation (Atari frames)")

    def __reduce__(self) -> tuple[Any, ...]:
        # a task's observation dict is a read-only mappingproxy, which pickle refuses: a schema
        # travels to worker processes and Ray tasks as its manifest JSON
        return (Schema.from_json, (self.to_json(),))

    @staticmethod
    def for_task(task: Any, image_encoding: str = "raw", observation: Any = None) -> Schema:
        """The schema of ``task``'s datasets: Atari stores single frames stacked at sample time."""
        obs = observation if observation is not None else task.observation_spec
        frame_stack = 1
        if DOMAINS[task.domain].stacked_frames and observation is None:
            frame_stack = obs.shape[-1]
            obs = ArraySpec(obs.shape[:-1], obs.dtype)
        return Schema(obs, task.action_spec, frame_stack, image_encoding, task.id)

    def observation_columns(self) -> dict[str, ArraySpec]:
        """The observation columns by file name (``observation`` or ``observation/<key>``) and
        spec."""
        if isinstance(self.observation, ArraySpec):
            return {"observation": self.observation}
        return {f"observation/{k}": v for k, v in self.observation.items()}

    def step_columns(self) -> dict[str, ArraySpec]:
        """Every per-step column and its spec: observations (unless frame-stacked Atari, whose
        frames are their own columns), action, reward, discount and the flags."""
        cols = {} if self.frame_stack > 1 else dict(self.observation_columns())
        cols["action"] = ArraySpec(self.action.shape, self.action.dtype)
        cols["reward"] = ArraySpec((), "float32")
        cols["discount"] = ArraySpec((), "float32")
        for f in FLAG_COLUMNS:
            cols[f] = ArraySpec((), "bool")
        return cols

    def frame_columns(self) -> dict[str, ArraySpec]:
        """The frame columns of frame-stacked (Atari) data, one frame per step plus each segment's
        prefix; empty otherwise."""
        return dict(self.observation_columns()) if self.frame_stack > 1 else {}

    def encoding(self, spec: ArraySpec) -> str:
        """How a column of ``spec`` is stored: ``zlib`` for uint8 images under a zlib schema, else
        ``raw``."""
        if self.image_encoding == "zlib" and spec.dtype == "uint8" and len(spec.shape) >= 2:
            return "zlib"
        return "raw"

    def files(self) -> list[str]:
        """Every file a dataset of this schema holds besides the manifest, relative to it."""
        out = []
        for name, spec in {**self.step_columns(), **self.frame_columns()}.items():
            if self.encoding(spec) == "zlib":
                out += [f"steps/{name}.zlib", f"steps/{name}.offsets.bin"]
            else:
                out.append(f"steps/{name}.bin")
        out += [f"segments/{k}.bin" for k in SEGMENT_INDEX]
        out += [f"segments/meta_{k}.bin" for k in METADATA_FIELDS]
        return sorted(out)

    def to_json(self) -> dict[str, Any]:
        """The schema as the manifest's ``schema`` object (``Schema.from_json`` reads it back)."""
        return {
            "observation": observation_spec_to_json(self.observation),
            "action": self.action.to_json(),
            "frame_stack": self.frame_stack,
            "image_encoding": self.image_encoding,
            "task_id": self.task_id,
        }

    @staticmethod
    def from_json(d: Any) -> Schema:
        """The schema of a manifest; anything the writer could not have written raises
        :class:`FieldError` naming the field (``schema.action.dtype``...)."""
        d = _obj(d, "schema")
        obs_json = _get(d, "observation", "schema")
        if isinstance(obs_json, Mapping) and "shape" in obs_json and "dtype" in obs_json:
            observation: ObservationSpec = _array_spec(obs_json, "schema.observation")
        else:
            obs_json = _obj(obs_json, "schema.observation")
            if not obs_json:
                raise FieldError("schema.observation", "is empty; a step needs an observation")
            observation = {}
            for key, spec in obs_json.items():
                _observation_key(key)
                observation[key] = _array_spec(spec, f"schema.observation.{key}")
        action = _action_spec(_get(d, "action", "schema"))
        frame_stack = whole_number(_get(d, "frame_stack", "schema"), "schema.frame_stack", 1)
        if frame_stack > MAX_FRAME_STACK:
            raise FieldError(
                "schema.frame_stack", f"is {frame_stack}; rlu stacks at most {MAX_FRAME_STACK}"
            )
        encoding = _get(d, "image_encoding", "schema")
        if encoding not in ENCODINGS:
            raise FieldError("schema.image_encoding", f"is {encoding!r}; use one of {ENCODINGS}")
        task_id = d.get("task_id")
        if task_id is not None and not isinstance(task_id, str):
            raise FieldError("schema.task_id", f"is {type(task_id).__name__}; a task id string")
        if frame_stack > 1 and not isinstance(observation, ArraySpec):
            raise FieldError("schema.frame_stack", "> 1 needs a single-array observation")
        return Schema(observation, action, frame_stack, encoding, task_id)


# --- strict reading of manifest values ----------------------------------------------------------
def _obj(v: Any, field: str) -> Mapping[str, Any]:
    if not isinstance(v, Mapping):
        raise FieldError(field, f"is a {type(v).__name__}; an object was expected")
    return v


def _get(d: Mapping[str, Any], key: str, field: str) -> Any:
    if key not in d:
        raise FieldError(f"{field}.{key}", "is missing")
    return d[key]


def whole_number(v: Any, field: str, lo: int = 0, hi: int = 1 << 48) -> int:
    """A whole number in [lo, hi] (JSON ``1e300`` or ``"5"`` are refused, not coerced)."""
    if isinstance(v, bool) or not isinstance(v, int):
        raise FieldError(field, f"is {v!r}; a whole number was expected")
    if not lo <= v <= hi:
        raise FieldError(field, f"is {v}; it must lie in [{lo}, {hi}]")
    return v


def _bound(v: Any, field: str) -> float:
    """An action bound: a number, infinite allowed (an unbounded Box), NaN not."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(float(v)):
        raise FieldError(field, f"is {v!r}; a number was expected")
    return float(v)


def _observation_key(key: Any) -> None:
    """Keys become paths under ``steps/observation/``: plain names joined by ``/`` only."""
    parts = key.split("/") if isinstance(key, str) else [""]
    if not all(_KEY_PART.fullmatch(p) and p not in (".", "..") for p in parts):
        raise FieldError(
            "schema.observation",
            f"has key {key!r}; keys are names of letters, digits, '_', '.', '+', '-' joined by '/'",
        )


def _array_spec(v: Any, field: str) -> ArraySpec:
    v = _obj(v, field)
    shape = _get(v, "shape", field)
    if not isinstance(shape, list) or len(shape) > MAX_RANK:
        raise FieldError(f"{field}.shape", f"is {shape!r}; a list of at most {MAX_RANK} sizes")
    dims = tuple(whole_number(x, f"{field}.shape", 0, MAX_STEP_ELEMENTS) for x in shape)
    if math.prod(dims) > MAX_STEP_ELEMENTS:
        raise FieldError(f"{field}.shape", f"is {list(dims)}: more than {MAX_STEP_ELEMENTS} values")
    dtype = _get(v, "dtype", field)
    if dtype not in DTYPES:
        raise FieldError(f"{field}.dtype", f"is {dtype!r}; use one of {', '.join(DTYPES)}")
    return ArraySpec(dims, dtype)


def _action_spec(v: Any) -> ActionSpec:
    base = _array_spec(v, "schema.action")
    if "num_values" in v:
        if base.shape != () or not np.issubdtype(np.dtype(base.dtype), np.integer):
            raise FieldError("schema.action", "is discrete (num_values) but not a scalar integer")
        n = whole_number(v["num_values"], "schema.action.num_values", 1, 1 << 31)
        return DiscreteSpec(base.shape, base.dtype, n)
    if "minimum" in v and "maximum" in v:
        lo = _bound(v["minimum"], "schema.action.minimum")
        hi = _bound(v["maximum"], "schema.action.maximum")
        if lo > hi:
            raise FieldError("schema.action", f"has minimum {lo} above maximum {hi}")
        return BoundedSpec(base.shape, base.dtype, lo, hi)
    raise FieldError("schema.action", "has neither num_values nor minimum / maximum")


# --- one segment as columns -------------------------------------------------------------------
def partial_dir(dest: Path) -> Path:
    """Where a writer builds ``dest`` before renaming it into place."""
    return dest.parent / f".{dest.name}.partial"


def segment_columns(schema: Schema, seg: Segment) -> dict[str, np.ndarray]:
    """``seg`` as the store's columns, checked against ``schema`` (keys, shapes, dtypes)."""
    n = len(seg)
    if n < 1:
        raise SpecError("a segment needs at least one step")
    unknown = set(seg.metadata) - set(METADATA_FIELDS)
    if unknown:
        raise SpecError(
            f"segment metadata has unknown key(s) {sorted(unknown)}; known: "
            f"{', '.join(METADATA_FIELDS)}"
        )
    cols: dict[str, np.ndarray] = {}
    obs = seg.observation
    if isinstance(schema.observation, ArraySpec):
        if isinstance(obs, Mapping):
            raise SpecError("observation is a dict but the schema stores one array")
        cols["observation"] = np.asarray(obs)
    else:
        if not isinstance(obs, Mapping):
            raise SpecError("observation is an array but the schema stores a dict")
        missing = set(schema.observation) - set(obs)
        extra = set(obs) - set(schema.observation)
        if missing or extra:
            raise SpecError(
                f"observation keys disagree with the schema: missing {sorted(missing)}, "
                f"unexpected {sorted(extra)}"
            )
        cols.update({f"observation/{k}": np.asarray(v) for k, v in obs.items()})
    if schema.frame_stack > 1:
        frames = cols["observation"]
        prefix = seg.frame_prefix
        if prefix is None:
            if not bool(seg.is_first[0]):
                raise SpecError(
                    "a segment that does not start an episode needs frame_prefix "
                    f"({schema.frame_stack - 1} frames before step 0)"
                )
            prefix = np.zeros((schema.frame_stack - 1, *frames.shape[1:]), frames.dtype)
        prefix = np.asarray(prefix)
        if prefix.shape[0] != schema.frame_stack - 1:
            raise SpecError(
                f"frame_prefix has {prefix.shape[0]} frames; the schema stacks "
                f"{schema.frame_stack}, so give {schema.frame_stack - 1}"
            )
        cols["observation"] = np.concatenate([prefix, frames])
    cols.update(
        action=np.asarray(seg.action),
        reward=np.asarray(seg.reward),
        discount=np.asarray(seg.discount),
        is_first=np.asarray(seg.is_first),
        is_last=np.asarray(seg.is_last),
        is_terminal=np.asarray(seg.is_terminal),
    )
    frame_specs = schema.frame_columns()
    specs = {**schema.step_columns(), **frame_specs}
    for name, spec in specs.items():
        v = cols[name]
        want_n = n + (schema.frame_stack - 1 if name in frame_specs else 0)
        if v.shape != (want_n, *spec.shape):
            raise SpecError(
                f"column {name!r} has shape {v.shape}; the schema wants "
                f"{(want_n, *spec.shape)} (steps first, then {spec.shape})"
            )
        check_cast(name, v.dtype, spec.dtype)
    return cols


def action_problem(spec: ActionSpec, action: np.ndarray) -> tuple[int, str] | None:
    """(first row, why) of ``action`` rows outside the action space, or None.

    Discrete actions must be whole numbers in [0, num_values); bounded ones lie in
    [minimum, maximum] up to float32 rounding (1e-6 relative).
    """
    a = np.asarray(action)
    if not a.size:
        return None
    flat = a.reshape(len(a), -1)
    if isinstance(spec, DiscreteSpec):
        bad = (flat < 0) | (flat >= spec.num_values)
        if a.dtype.kind == "f":
            bad |= ~(np.isfinite(flat) & (flat == np.round(flat)))
        want = f"whole numbers in [0, {spec.num_values})"
    elif isinstance(spec, BoundedSpec):
        lo, hi = spec.minimum, spec.maximum
        tol_lo, tol_hi = 1e-6 * max(1.0, abs(lo)), 1e-6 * max(1.0, abs(hi))
        with np.errstate(invalid="ignore"):
            bad = ~((flat >= lo - tol_lo) & (flat <= hi + tol_hi))  # NaN is outside too
        want = f"values in [{lo:g}, {hi:g}]"
    else:
        return None
    rows = np.flatnonzero(np.any(bad, axis=1))
    if not rows.size:
        return None
    i = int(rows[0])
    return i, f"action {a[i].tolist()} is outside the action space ({want})"


def check_cast(name: str, have: Any, want: str) -> None:
    """Values of dtype ``have`` may be stored in a ``want`` column (no complex -> float, float ->
    int or bool, ...)."""
    if not np.can_cast(have, want, casting="same_kind"):
        raise SpecError(f"column {name!r} has dtype {have}; the schema wants {want}")
