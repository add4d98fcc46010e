"""The D4RL-style flat transition dict, out of and into the store.

Keys: ``observations``, ``actions``, ``rewards``, ``terminals``, ``timeouts``,
``next_observations``; a dict observation is flattened as ``observations/<key>`` and
``next_observations/<key>`` (``observations/walker/joints_pos``).

Export writes one row per transition of the SARSA view, to the file type its name says:
``.hdf5`` / ``.h5`` is an HDF5 file in D4RL's layout (one dataset per key at the top level, read
by D4RL's ``get_dataset`` and every loader copied from it: ``visititems`` over the datasets,
``[:]``), ``.npz`` a numpy archive of the same arrays; any other name is refused. In the files a
dict observation whose arrays share one floating dtype is one ``observations`` array (N, D), the
keys flattened in the task's key order as D4RL's, d3rlpy's and dm_control's
``flatten_observation`` lay them out (import splits it back by the task's keys); other dict
observations (a camera beside features) keep one array per key. ``metadata/rlu/...`` records the
task id, the observation keys and sizes, the manifest's provenance (JSON) and the export id of
the sidecar ``<file>.rlu.npz`` that holds what the file cannot (each segment's final step,
one-step segments, metadata, attachments: rlu.data.roundtrip); import reads both back. The file
is written a block of rows at a time. A dataset imported from a D4RL file is exported in that
file's layout (``source/d4rl.json``, below). Release windows and actions outside the action space
are refused (rlu.data.roundtrip.check_exportable).

``terminals[i]`` is True when transition i enters a terminal state (discount 0); ``timeouts[i]`` is
True on the last transition of every other episode, so that import cuts the rows back into the
same episodes.

Import cuts episodes at terminals and timeouts, and also wherever ``next_observations[i]`` differs
from ``observations[i + 1]`` (files in the wild miss some timeouts); a trailing run with neither
counts as truncated. Files without ``next_observations`` are cut at terminals and timeouts only
and read as d3rlpy reads them: after a terminal the final observation is zeros (not known); a
timeout row (or a trailing run's last row) is the episode's final step: it holds the final
observation, and its action and reward, which no transition uses, stay there (d3rlpy counts that
reward in the return and the returns-to-go). Frame stacks must continue each other (rlu stores
each frame once). What the store does not hold is kept in the dataset's ``source/d4rl.json`` and
``.npz``: the file's arrays in order with their dtypes, shapes, HDF5 storage and attributes, its
other arrays (``infos/*``, ``metadata/*``), step arrays the store's dtypes would change (float64
rewards), and the rows whose ``timeouts`` flag differs from the episodes' ends; export gives the
file back from them.

Import is wary of the file (rlu.data.foreign): every array's declared shape is checked against
the others and against the task's schema before a row is read, then the rows are read, cut and
written a block at a time, so memory holds one block and one episode (at most
``EPISODE_LENGTH_FACTOR`` times the task's episode length, and ``MAX_EPISODE_BYTES``) whatever a
small compressed file inflates to.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import zipfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.foreign import (
    EPISODE_LENGTH_FACTOR,
    MAX_EPISODE_BYTES,
    ArrayColumn,
    Column,
    H5Column,
    NpzFile,
    episode_limit,
    finite_array,
    fits,
    flag_array,
    hdf5_datasets,
    iter_blocks,
    open_hdf5,
    real_array,
    real_dtype,
    with_final_step,
)
from rlu.data.store import Dataset, DatasetWriter, Schema
from rlu.data.store.schema import action_problem
from rlu.data.views import DatasetView, TransitionView
from rlu.domains import DOMAINS
from rlu.segments import Segment, make_episode
from rlu.system import install_hint
from rlu.types import ArraySpec, FormatError, RluError, SpecError

REQUIRED = ("actions", "rewards", "terminals", "timeouts")


def to_d4rl(ds: Dataset) -> dict[str, np.ndarray]:
    view = TransitionView(ds)
    ids = np.arange(len(view))
    b = view.batch(ids)
    seg, _ = view.index.locate(ids)
    last_of_segment = np.zeros(len(ids), bool)
    if len(ids):
        last_of_segment[np.asarray(view.index.cum[1:]) - 1] = True
        last_of_segment &= view.index.counts[seg] > 0
    terminals = b.discount == 0
    out: dict[str, np.ndarray] = {}
    for prefix, obs in (("observations", b.observation), ("next_observations", b.next_observation)):
        if isinstance(obs, Mapping):
            out.update({f"{prefix}/{k}": v for k, v in obs.items()})
        else:
            out[prefix] = obs
    out["actions"] = b.action
    out["rewards"] = b.reward
    out["terminals"] = terminals
    out["timeouts"] = last_of_segment & ~terminals
    return out


HDF5_SUFFIXES = (".hdf5", ".h5")
STEP_NAMES = ("observations", "next_observations", "actions", "rewards", "terminals", "timeouts")
RLU_PREFIX = "metadata/rlu/"
"""rlu's own entries in the D4RL files it writes (task, provenance, the export id): skipped on
import, written again on export."""


def _flat_order(schema: Schema) -> list[str] | None:
    """The key order import splits a flat ``observations`` by (the task's), or None when the
    stored keys are not the task's (RWRL's extra challenge features: kept one array per key)."""
    from rlu.tasks import get_task

    spec = _dict_spec(schema)
    try:
        task = Schema.for_task(get_task(schema.task_id or "")).observation
    except RluError:
        return list(spec)  # no registered task: import names one; keep ours
    if not isinstance(task, Mapping):
        return None  # the task stores one array
    return list(task) if set(task) == set(spec) else None


def flat_spec(schema: Schema) -> dict[str, ArraySpec]:
    """The schema's observation keys in the order a flat array (or a tuple) holds them: the
    task's order (dm_control's ``flatten_observation``), which a schema read back from a manifest
    (keys sorted) does not keep."""
    spec = _dict_spec(schema)
    return {k: spec[k] for k in _flat_order(schema) or spec}


def _dict_spec(schema: Schema) -> Mapping[str, ArraySpec]:
    """The schema's dict observation spec: what the flat key orders are of."""
    if not isinstance(schema.observation, Mapping):
        raise RluError(f"task {schema.task_id}: one observation array has no keys (a bug in rlu)")
    return schema.observation


def _flat_keys(schema: Schema) -> list[str] | None:
    """The keys a float dict observation is flattened in (one ``observations`` array), or None
    when the observation stays one array per key (mixed dtypes, a camera, RWRL's extra keys)."""
    spec = schema.observation
    if not isinstance(spec, Mapping):
        return None
    keys = _flat_order(schema)
    dtypes = {np.dtype(s.dtype) for s in spec.values()}
    if keys is None or len(dtypes) != 1 or not np.issubdtype(dtypes.pop(), np.floating):
        return None
    return keys


@dataclasses.dataclass
class _Array:
    """One array of a D4RL file to write: its name, dtype and shape, and where its values come
    from (``rows``: the dataset's steps; ``kept``: the array an import kept in ``source/``;
    ``value``: a small value in hand)."""

    name: str
    dtype: np.dtype
    shape: tuple[int, ...]
    origin: str
    value: Any = None
    storage: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    attrs: list = dataclasses.field(default_factory=list)
    compress: bool = False


class _Rows:
    """The rows of a D4RL file of ``ds``: one per transition, and with ``final_rows`` (D4RL's
    layout without ``next_observations``) one more for the final step of each truncated
    segment (its observation, and the action and reward kept there)."""

    def __init__(self, ds: Dataset, final_rows: bool):
        self.ds, self.view = ds, DatasetView(ds)
        self.start = np.asarray(ds.start, np.int64)
        self.length = np.asarray(ds.length, np.int64)
        last = self.start + self.length - 1
        self.terminal = np.asarray(ds.column("is_terminal"))[last]
        self.final_rows = final_rows
        self.rows = self.length - 1 + (final_rows & ~self.terminal)
        self.in_file = self.rows > 0
        self.cum = np.concatenate([[0], np.cumsum(self.rows)])
        self.n = int(self.cum[-1])

    def locate(self, a: int, b: int) -> dict[str, np.ndarray]:
        r = np.arange(a, b, dtype=np.int64)
        seg = np.searchsorted(self.cum, r, side="right") - 1
        k = r - self.cum[seg]
        last_row = k == self.rows[seg] - 1
        final = k == self.length[seg] - 1  # only with final_rows: the final step's row
        terminal = last_row & self.terminal[seg] & ~final
        return {"seg": seg, "step": self.start[seg] + k, "terminal": terminal,
                "timeout": last_row & ~terminal}  # fmt: skip


class _Block:
    """The values of every array for rows ``a .. b - 1``, each computed once."""

    def __init__(self, rows: _Rows, a: int, b: int, flat: list[str] | None, flips: np.ndarray):
        self.rows, self.a, self.b, self.flat = rows, a, b, flat
        self.at = rows.locate(a, b)
        self.flips = flips[(flips >= a) & (flips < b)] - a
        self.memo: dict[str, Any] = {}

    def _obs(self, which: str) -> Any:
        if which not in self.memo:
            step = self.at["step"] + (1 if which == "next_observations" else 0)
            self.memo[which] = self.rows.view.observation(self.at["seg"], step)
        return self.memo[which]

    def values(self, name: str) -> np.ndarray:
        top, _, key = name.partition("/")
        if top in ("observations", "next_observations"):
            obs = self._obs(top)
            if key:
                return obs[key]
            if isinstance(obs, Mapping):
                parts = [np.asarray(obs[k]).reshape(self.b - self.a, -1) for k in self.flat or obs]
                return np.concatenate(parts, axis=1)
            return obs
        if name == "actions":
            return np.take(self.rows.ds.column("action"), self.at["step"], axis=0)
        if name == "rewards":
            return np.take(self.rows.ds.column("reward"), self.at["step"])
        if name == "terminals":
            return self.at["terminal"]
        if name == "timeouts":
            t = self.at["timeout"].copy()
            t[self.flips] = ~t[self.flips]
            return t
        raise RluError(f"D4RL export: no rows for array {name!r} (a bug in rlu)")


def _default_arrays(ds: Dataset, n: int, flat: list[str] | None) -> list[_Array]:
    schema = ds.schema
    out = []
    for top in ("observations", "next_observations"):
        spec = schema.observation
        if flat is not None:
            spec = _dict_spec(schema)
            size = sum(spec[k].size for k in flat)
            out.append(_Array(top, np.dtype(spec[flat[0]].dtype), (n, size), "rows"))
        elif isinstance(spec, Mapping):
            for k, s in spec.items():
                out.append(_Array(f"{top}/{k}", np.dtype(s.dtype), (n, *s.shape), "rows"))
        else:
            shape = (*spec.shape, schema.frame_stack) if schema.frame_stack > 1 else spec.shape
            gzip = {"compression": "gzip", "compression_opts": 1} if spec.dtype == "uint8" else {}
            out.append(_Array(top, np.dtype(spec.dtype), (n, *shape), "rows", storage=gzip))
    act = schema.action
    out.append(_Array("actions", np.dtype(act.dtype), (n, *act.shape), "rows"))
    out.append(_Array("rewards", np.dtype("float32"), (n,), "rows"))
    out.append(_Array("terminals", np.dtype(bool), (n,), "rows"))
    out.append(_Array("timeouts", np.dtype(bool), (n,), "rows"))
    return out


def _rlu_arrays(ds: Dataset, flat: list[str] | None, export_id: str) -> list[_Array]:
    import json

    def text(name: str, value: Any) -> _Array:
        a = np.asarray(value)
        return _Array(RLU_PREFIX + name, a.dtype, a.shape, "value", a)

    out = [
        text("task_id", ds.schema.task_id or ""),
        text("provenance", json.dumps(ds.manifest.get("provenance", {}), sort_keys=True)),
        text("export_id", export_id),
    ]
    if flat is not None:
        spec = _dict_spec(ds.schema)
        out.append(text("observation_keys", flat))
        out.append(text("observation_sizes", [spec[k].size for k in flat]))
    return out


def _source_arrays(info: Mapping[str, Any], n: int, where: str) -> list[_Array]:
    """The arrays of the file an import kept the layout of (``source/d4rl.json``)."""
    out = []
    for e in info["entries"]:
        shape = tuple(int(x) for x in e["shape"]) if e.get("shape") is not None else ()
        if e["origin"] == "rows" and (not shape or shape[0] != n):
            raise FormatError(
                f"{where}: source/d4rl.json says array {e['name']!r} has {shape[:1]} rows; the "
                f"dataset's episodes make {n}: re-import the file"
            )
        out.append(
            _Array(
                e["name"],
                np.dtype(e["dtype"]) if e.get("dtype") is not None else np.dtype("O"),
                shape,
                e["origin"],
                e.get("value"),
                e.get("storage") or {},
                e.get("attrs") or [],
                bool(e.get("compress")),
            )
        )
    return out


def export_d4rl(
    ds: Dataset,
    out: str | os.PathLike,
    overwrite: bool = False,
    note: Any = None,
) -> Path:
    """Write ``ds`` as a D4RL file: HDF5 for a ``.hdf5``/``.h5`` name, an .npz archive for
    ``.npz`` (see the module doc), a block of rows at a time, atomically (an unpredictable
    temporary, then rename), with its sidecar ``<out>.rlu.npz`` (rlu.data.roundtrip; ``note``
    gets the one line saying what it holds). A dataset imported from a D4RL file is written
    back in that file's layout (``source/d4rl.json``). Release windows and actions outside the
    action space are refused before anything is written. ``out`` is checked first
    (rlu.files.check_output_file): not inside the dataset, not an existing file unless
    ``overwrite``, and then only one rlu wrote; its folder is made if missing."""
    from rlu.data.roundtrip import (
        check_exportable,
        new_export_id,
        read_source,
        sidecar_path,
        write_sidecar,
    )
    from rlu.files import atomic_path, check_output_file, interrupts_deferred, make_folder
    from rlu.locks import OutputLock

    if not str(out).strip():
        raise RluError("-o is empty; give the D4RL file's path")
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in (*HDF5_SUFFIXES, ".npz"):
        raise RluError(
            f"{out}: unknown D4RL file type {out.suffix or '(no extension)'!r}; name the output "
            "X.hdf5 (HDF5, D4RL's own format) or X.npz (a numpy archive)"
        )
    check_output_file(out, [ds.path], overwrite, is_rlu_d4rl, "D4RL file")
    side = sidecar_path(out)
    check_output_file(side, [ds.path], True, is_sidecar, "sidecar")
    h5py = _require_h5py("writing D4RL .hdf5 files") if suffix in HDF5_SUFFIXES else None
    check_exportable(ds, "D4RL", windows=False)
    source = read_source(ds, "d4rl")
    info = source[0] if source else None
    rows = _Rows(ds, final_rows=bool(info is not None and not info["next_observations"]))
    flat = info.get("flat_keys") if info else _flat_keys(ds.schema)
    if source is not None:
        info, z = source
        arrays = _source_arrays(info, rows.n, str(ds.path))
        flips = z.read("timeouts_flipped") if "timeouts_flipped" in z.infos else None
    else:
        arrays = _default_arrays(ds, rows.n, flat)
        flips = None
    flips = np.zeros(0, np.int64) if flips is None else np.asarray(flips, np.int64)
    export_id = new_export_id()
    arrays += _rlu_arrays(ds, flat, export_id)
    held = ~rows.in_file | (rows.final_rows & rows.terminal)  # final observations the file lacks
    make_folder(out.parent)
    with OutputLock(out, "export file"):  # one writer per output file
        try:
            with atomic_path(out, suffix=True) as tmp:
                if h5py is not None:
                    f = h5py.File(tmp, "w")
                    try:
                        _write_hdf5(f, arrays, rows, flat, flips, source, info)
                    finally:
                        with interrupts_deferred():  # a Ctrl-C here is raised after the close
                            f.close()
                else:
                    _write_npz(tmp, arrays, rows, flat, flips, source)
                what = write_sidecar(ds, side, "d4rl", export_id, held)
        finally:
            if source is not None:
                source[1].__exit__()
    if note is not None:
        note(
            f"D4RL files cannot hold {', '.join(what)}: kept in {side.name} beside {out.name}, "
            "which rlu import reads back"
        )
    return out


def _row_bytes(arrays: list[_Array]) -> int:
    return sum(math.prod(a.shape[1:]) * a.dtype.itemsize for a in arrays if a.origin == "rows")


def _as_array(values: Any, a: _Array) -> np.ndarray:
    v = np.asarray(values)
    return v.astype(a.dtype, copy=False).reshape(len(v), *a.shape[1:])


def _kept(source: Any, a: _Array) -> Column:
    z = source[1]
    key = a.value
    if key not in z.infos:
        raise FormatError(f"{z.path}: no kept array {key!r} for {a.name!r}; re-import the file")
    col = z.column(key)
    if tuple(col.shape) != a.shape or col.dtype != a.dtype:
        raise FormatError(f"{z.path}: kept array {key!r} is not {a.dtype}{list(a.shape)}")
    return col


def release_all(ds: Dataset) -> None:
    from rlu.data.roundtrip import release_all as release

    release(ds)


def _write_hdf5(f: Any, arrays: list[_Array], rows: _Rows, flat: Any, flips: Any, source: Any,
                info: Any) -> None:  # fmt: skip
    import h5py

    for g in (info or {}).get("groups", []):
        grp = f.require_group(g["name"]) if g["name"] else f
        _set_attrs(grp, g.get("attrs") or [], source)
    made = {}
    for a in arrays:
        if a.origin == "value":
            data = a.value
            if np.asarray(data).dtype.kind == "U":  # h5py stores str as variable-length UTF-8
                data = np.asarray(data).tolist()
            f.create_dataset(a.name, data=data)
        elif a.origin == "strings":
            dt = h5py.string_dtype(a.storage.get("encoding", "utf-8"), a.storage.get("length"))
            f.create_dataset(a.name, data=a.value, dtype=dt)
        else:
            st = {k: v for k, v in a.storage.items() if v is not None}
            if "chunks" in st:
                st["chunks"] = tuple(st["chunks"])
            if "maxshape" in st:
                st["maxshape"] = tuple(None if x is None else int(x) for x in st["maxshape"])
            made[a.name] = f.create_dataset(a.name, shape=a.shape, dtype=a.dtype, **st)
        _set_attrs(f[a.name], a.attrs, source)
    steps = [a for a in arrays if a.origin == "rows"]
    for lo, hi in iter_blocks(rows.n, _row_bytes(steps)):
        block = _Block(rows, lo, hi, flat, flips)
        for a in steps:
            made[a.name][lo:hi] = _as_array(block.values(a.name), a)
        release_all(rows.ds)
    for a in arrays:
        if a.origin == "kept":
            col = _kept(source, a)
            if a.shape:
                for lo, hi in iter_blocks(a.shape[0], max(1, col.row_bytes)):
                    made[a.name][lo:hi] = col.rows(lo, hi)
            else:
                made[a.name][()] = col.rows(0, 1)


def _set_attrs(obj: Any, attrs: list, source: Any) -> None:
    for at in attrs:
        if at["kind"] == "str":
            obj.attrs[at["name"]] = at["value"]
        elif at["kind"] == "strs":
            import h5py

            obj.attrs.create(at["name"], at["value"], dtype=h5py.string_dtype())
        else:
            obj.attrs[at["name"]] = source[1].read(at["key"])


def _write_npz(tmp: Path, arrays: list[_Array], rows: _Rows, flat: Any, flips: Any,
               source: Any) -> None:  # fmt: skip
    from rlu.data.roundtrip import NpzWriter

    with NpzWriter(tmp) as w:
        for a in arrays:
            if a.origin == "value":
                w.add(a.name, np.asarray(a.value), a.compress)
            elif a.origin == "strings":
                w.add(a.name, np.asarray(a.value, dtype=str), a.compress)
            elif a.origin == "kept":
                col = _kept(source, a)
                with w.member(a.name, a.shape, a.dtype, a.compress) as write:
                    if a.shape:
                        for lo, hi in iter_blocks(a.shape[0], max(1, col.row_bytes)):
                            write(col.rows(lo, hi))
                    else:
                        write(col.rows(0, 1))
            else:
                with w.member(a.name, a.shape, a.dtype, a.compress) as write:
                    for lo, hi in iter_blocks(rows.n, _row_bytes([a]) * 2):
                        write(_as_array(_Block(rows, lo, hi, flat, flips).values(a.name), a))
                        release_all(rows.ds)


def is_rlu_d4rl(path: Path) -> bool:
    """Whether ``path`` is a D4RL file rlu wrote (it holds ``metadata/rlu/task_id``)."""
    key = RLU_PREFIX + "task_id"
    try:
        if path.suffix.lower() == ".npz":
            with NpzFile(path) as z:
                return key in z.infos
        f = open_hdf5(path, "a D4RL file rlu wrote")
        try:
            return key in f
        finally:
            f.close()
    except (RluError, OSError):
        return False


def is_sidecar(path: Path) -> bool:
    """Whether ``path`` is the sidecar of an rlu export."""
    try:
        with NpzFile(path) as z:
            return "rlu/sidecar" in z.infos
    except (RluError, OSError):
        return False


def _require_h5py(what: str) -> Any:
    try:
        import h5py
    except ImportError:
        raise RluError(f"{what} needs h5py: {install_hint('interop')}") from None
    return h5py


# --- import: the file's arrays as columns, checked before a row is read -------------------------
@dataclasses.dataclass
class _Layout:
    """The columns of a D4RL file, their shapes checked against each other (and the schema)."""

    n: int
    obs: dict[str, Column]
    """'' -> the one ``observations`` array, or key -> ``observations/<key>``."""
    nxt: dict[str, Column] | None
    actions: Column
    rewards: Column
    terminals: Column
    timeouts: Column

    @property
    def row_bytes(self) -> int:
        cols = [*self.obs.values(), *(self.nxt or {}).values()]
        cols += [self.actions, self.rewards, self.terminals, self.timeouts]
        return sum(c.row_bytes for c in cols)


def _obs_columns(cols: Mapping[str, Column], prefix: str, n: int, where: str) -> dict:
    if prefix in cols:
        return {"": _checked_rows(cols[prefix], prefix, where, n)}
    keys = {k[len(prefix) + 1 :]: k for k in cols if k.startswith(prefix + "/")}
    if not keys:
        raise FormatError(f"{where}: no {prefix!r} array and no '{prefix}/<key>' arrays")
    return {k: _checked_rows(cols[full], full, where, n) for k, full in sorted(keys.items())}


def _checked_rows(c: Column, name: str, where: str, n: int) -> Column:
    real_dtype(c.dtype, name, where)
    if not c.shape or c.shape[0] != n:
        raise FormatError(
            f"{where}: {name!r} has {c.shape[0] if c.shape else 0} rows where the other arrays "
            f"have {n}; every array needs one row per step"
        )
    return c


def _layout(cols: Mapping[str, Column], where: str) -> _Layout:
    """Shapes and dtypes as declared, before anything is read (see the module docstring)."""
    missing = [k for k in REQUIRED if k not in cols]
    if missing:
        raise FormatError(
            f"{where}: missing array(s) {missing}; a D4RL dict has {', '.join(REQUIRED)}"
        )
    rewards = cols["rewards"]
    real_dtype(rewards.dtype, "rewards", where)
    if len(rewards.shape) not in (1, 2) or math.prod(rewards.shape[1:]) != 1:
        raise FormatError(f"{where}: 'rewards' has shape {rewards.shape}; one reward per row")
    n = rewards.shape[0]
    if n == 0:
        raise FormatError(f"{where}: 'rewards' has no rows; there is nothing to import")
    actions = _checked_rows(cols["actions"], "actions", where, n)
    flags = {}
    for name in ("terminals", "timeouts"):
        flags[name] = _checked_rows(cols[name], name, where, n)
        if flags[name].row_bytes != flags[name].dtype.itemsize:
            raise FormatError(f"{where}: {name!r} has shape {flags[name].shape}; one flag per row")
    obs = _obs_columns(cols, "observations", n, where)
    nxt = None
    if "next_observations" in cols or any(k.startswith("next_observations/") for k in cols):
        nxt = _obs_columns(cols, "next_observations", n, where)
        if set(obs) != set(nxt):
            raise FormatError(
                f"{where}: 'observations' and 'next_observations' differ in their keys"
            )
        if any(obs[k].shape != nxt[k].shape for k in obs):
            raise FormatError(f"{where}: 'observations' and 'next_observations' differ in shape")
    return _Layout(n, obs, nxt, actions, rewards, flags["terminals"], flags["timeouts"])


def _check_schema(lay: _Layout, schema: Schema, where: str) -> None:
    """Every row's declared size is the task's: nothing of another shape is read."""
    k = schema.frame_stack
    task = schema.task_id or "the schema"

    def want(c: Column, name: str, size: int, shape: Any) -> None:
        if math.prod(c.shape[1:]) != size:
            raise FormatError(
                f"{where}: {name!r} has rows of shape {c.shape[1:]}; task {task} stores {shape}"
            )

    want(lay.actions, "actions", schema.action.size, schema.action.shape)
    spec = schema.observation
    if isinstance(spec, ArraySpec):
        if "" not in lay.obs:
            raise FormatError(
                f"{where}: 'observations/<key>' arrays (dict observations); task {task} stores "
                "one 'observations' array"
            )
        if k > 1 and (len(lay.obs[""].shape) < 3 or lay.obs[""].shape[-1] != k):
            raise FormatError(
                f"{where}: frame-stacked import needs one 'observations' array of stacks "
                f"(..., {k}), newest frame last; it has rows of {lay.obs[''].shape[1:]}"
            )
        want(lay.obs[""], "observations", spec.size * k, (*spec.shape, k) if k > 1 else spec.shape)
        return
    if "" in lay.obs:
        size = sum(s.size for s in spec.values())
        if len(lay.obs[""].shape) != 2 or lay.obs[""].shape[1] != size:
            raise FormatError(
                f"{where}: 'observations' has rows of shape {lay.obs[''].shape[1:]}; task {task} "
                f"stores its keys {list(flat_spec(schema))} flattened to ({size},)"
            )
        return
    unknown, absent = sorted(set(lay.obs) - set(spec)), sorted(set(spec) - set(lay.obs))
    if unknown or absent:
        raise FormatError(
            f"{where}: observation keys differ from task {task}'s: unknown "
            f"{['observations/' + u for u in unknown]}, missing "
            f"{['observations/' + a for a in absent]}"
        )
    for key, c in lay.obs.items():
        want(c, f"observations/{key}", spec[key].size, spec[key].shape)


class _Episode:
    """The rows of the episode being cut, gathered block by block (bounded in steps and bytes)."""

    def __init__(self, where: str, max_steps: int | None, frame_stack: int):
        self.where, self.max_steps, self.k = where, max_steps, frame_stack
        self.start = 0
        self.parts: dict[str, list[np.ndarray]] = {}
        self.steps = self.bytes = 0
        self.prefix: np.ndarray | None = None
        self.last_stack: np.ndarray | None = None

    def add(self, row0: int, block: Mapping[str, np.ndarray], a: int, b: int) -> None:
        if b <= a:
            return
        if not self.steps:
            self.start = row0 + a
            if self.k > 1:  # the first stack's older frames: the segment's frame prefix
                self.prefix = np.moveaxis(block["obs/"][a, ..., : self.k - 1], -1, 0).copy()
        for name, v in block.items():
            if name.startswith("obs/") and self.k > 1:
                v = v[..., -1]
            part = np.array(v[a:b])  # a copy: a view would keep the whole block alive
            self.parts.setdefault(name, []).append(part)
            self.bytes += part.nbytes
        self.steps += b - a
        if self.max_steps is not None and self.steps > self.max_steps:
            raise FormatError(
                f"{self.where}: the episode starting at row {self.start} runs past "
                f"{self.max_steps} steps without a terminal or timeout ({EPISODE_LENGTH_FACTOR} "
                "times its task's episode length): the file lacks its episode ends (D4RL's "
                "'timeouts') or is not what it claims"
            )
        if self.bytes > MAX_EPISODE_BYTES:
            raise FormatError(
                f"{self.where}: the episode starting at row {self.start} holds more than "
                f"{MAX_EPISODE_BYTES} bytes without a terminal or timeout: the file lacks its "
                "episode ends (D4RL's 'timeouts') or is not what it claims"
            )

    def take(self) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
        out = {k: np.concatenate(v) if len(v) > 1 else v[0] for k, v in self.parts.items()}
        prefix = self.prefix
        self.parts, self.steps, self.bytes, self.prefix = {}, 0, 0, None
        return out, prefix


def _iter_segments(
    lay: _Layout,
    where: str,
    frame_stack: int = 1,
    max_steps: int | None = None,
    on_block: Any = None,
) -> Iterator[Segment]:
    """Cut the rows into whole episodes (module docstring), reading a block of rows at a time:
    one block and one episode are held, whatever the file's length. ``on_block(a, terminals,
    timeouts, ends)`` sees each block's flags and where its episodes end."""
    if frame_stack > 1 and lay.nxt is None:
        raise FormatError(f"{where}: frame-stacked import needs 'next_observations'")
    n, ep = lay.n, _Episode(where, max_steps, frame_stack)
    single = "" in lay.obs
    for a, b in iter_blocks(n, lay.row_bytes):
        block = {
            "rewards": finite_array(lay.rewards.rows(a, b), "rewards", where).reshape(-1),
            "actions": real_array(lay.actions.rows(a, b), "actions", where),
            "terminals": flag_array(lay.terminals.rows(a, b), "terminals", where),
        }
        timeouts = flag_array(lay.timeouts.rows(a, b), "timeouts", where)
        ends = block["terminals"] | timeouts
        hi = min(n, b + 1) if lay.nxt is not None else b  # one row ahead: does it continue?
        for key, c in lay.obs.items():
            name = "observations" + (f"/{key}" if key else "")
            block[f"obs/{key}"] = real_array(c.rows(a, hi), name, where)
        if lay.nxt is not None:
            cont = np.ones(hi - a - 1, bool)
            for key, c in lay.nxt.items():
                name = "next_observations" + (f"/{key}" if key else "")
                nxt = block[f"next/{key}"] = real_array(c.rows(a, b), name, where)
                m = len(cont)
                if m:
                    succ = block[f"obs/{key}"][1:]
                    cont &= (nxt[:m].reshape(m, -1) == succ.reshape(m, -1)).all(axis=1)
                block[f"obs/{key}"] = block[f"obs/{key}"][: b - a]
            ends[: len(cont)] |= ~cont  # a row its successor does not continue ends an episode
        if b == n:
            ends[-1] = True
        if on_block is not None:
            on_block(a, block["terminals"], timeouts, ends)
        if frame_stack > 1:
            _check_stacks(block, ends, ep, where, a)
        stored = {k: v for k, v in block.items() if not k.startswith("next/")}
        s = 0
        for e in np.flatnonzero(ends).tolist():
            ep.add(a, stored, s, e + 1)
            last = {k[5:]: v[e : e + 1] for k, v in block.items() if k.startswith("next/")}
            yield _segment(*ep.take(), last, single, lay.nxt is not None, frame_stack)
            s = e + 1
        ep.add(a, stored, s, b - a)


def _check_stacks(block: dict, ends: np.ndarray, ep: _Episode, where: str, row0: int) -> None:
    """Consecutive rows of an episode hold frame stacks that share frames (rlu stores each frame
    once): row t's older frames are row t - 1's newer ones, and a next observation's are its
    row's. Independent stacks are refused instead of being stored as their newest frames."""
    obs = block["obs/"]
    m = len(obs)
    if not m:
        return
    prev = np.concatenate([ep.last_stack[None], obs[:-1]]) if ep.last_stack is not None else None
    rows = np.arange(m)
    if prev is None:
        prev, rows, cur = obs[:-1], rows[1:], obs[1:]
        starts = ends[: m - 1]  # row r + 1 starts an episode when row r ends one
    else:
        cur = obs
        starts = np.concatenate([[False], ends[: m - 1]])
    same = (cur[..., :-1] == prev[..., 1:]).reshape(len(cur), -1).all(axis=1)
    bad = np.flatnonzero(~same & ~starts)
    if bad.size:
        r = row0 + int(rows[bad[0]])
        raise FormatError(
            f"{where}: row {r} does not continue the frame stack of row {r - 1}; rlu stores "
            "each frame once and cannot import independent stacks"
        )
    if "next/" in block:
        nxt = block["next/"]
        ok = (nxt[..., :-1] == obs[..., 1:]).reshape(m, -1).all(axis=1)
        if not ok.all():
            r = row0 + int(np.flatnonzero(~ok)[0])
            raise FormatError(
                f"{where}: row {r}'s next observation does not continue its frame stack; rlu "
                "stores each frame once and cannot import independent stacks"
            )
    ep.last_stack = None if ends[m - 1] else obs[-1].copy()


def _segment(
    rows: dict[str, np.ndarray],
    prefix: np.ndarray | None,
    last_next: dict[str, np.ndarray],
    single: bool,
    has_next: bool,
    frame_stack: int,
) -> Segment:
    """One episode's rows as a segment: with next observations, the last one ends it; without,
    a terminal ends in zeros, and a timeout row holds the final observation, its action and
    reward kept in the final step (see ``with_final_step``)."""
    obs = {k[4:]: v for k, v in rows.items() if k.startswith("obs/")}
    actions, rewards = rows["actions"], rows["rewards"]
    terminal = bool(rows["terminals"][-1])

    def one(d: dict[str, np.ndarray]) -> Any:
        return d[""] if single else d

    if has_next:
        if frame_stack > 1:
            last_next = {k: v[..., -1] for k, v in last_next.items()}
        full = {k: np.concatenate([v, last_next[k]]) for k, v in obs.items()}
        return make_episode(one(full), actions, rewards, terminal, frame_prefix=prefix)
    if terminal:
        full = {k: np.concatenate([v, np.zeros_like(v[:1])]) for k, v in obs.items()}
        return make_episode(one(full), actions, rewards, True)
    seg = make_episode(one(obs), actions[:-1], rewards[:-1], False)
    return with_final_step(seg, actions[-1], float(rewards[-1]))


def d4rl_segments(
    d: Mapping[str, np.ndarray], frame_stack: int = 1, where: str = "D4RL dict"
) -> list[Segment]:
    """Cut a D4RL-style dict into whole episodes (see the module docstring)."""
    cols = {k: ArrayColumn(v, k, where) for k, v in d.items()}
    return list(_iter_segments(_layout(cols, where), where, frame_stack))


def _want(name: str) -> bool:
    """The step arrays of a D4RL file (``infos/``, ``metadata/`` and the rest are kept aside)."""
    top = name.split("/", 1)[0]
    return top in ("observations", "next_observations") or name in REQUIRED


MAX_STRING_VALUES = 1 << 16
MAX_ATTR_BYTES = 16 << 20


@dataclasses.dataclass
class _File:
    """A D4RL file opened for import: its step arrays as columns, and everything else it holds
    (in file order) for ``source/d4rl.json``."""

    container: str
    path: Path | None
    cols: dict[str, Column]
    entries: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    extra: dict[str, Column] = dataclasses.field(default_factory=dict)
    groups: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    attr_arrays: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    rlu: dict[str, str] = dataclasses.field(default_factory=dict)
    skipped: list[str] = dataclasses.field(default_factory=list)


def _small_text(col: Column, where: str) -> str | None:
    """A short text entry of rlu's (``metadata/rlu/task_id``...), or None."""
    if col.dtype.kind not in "SU" or math.prod(col.shape) > 1 or col.nbytes > 1 << 16:
        return None
    v = np.asarray(col.read()).reshape(-1)
    if not v.size:
        return None
    x = v[0]
    return x.decode("utf-8", "replace") if isinstance(x, bytes) else str(x)


def _h5_attrs(obj: Any, f: _File, where: str, budget: list[int]) -> list[dict[str, Any]]:
    import h5py

    out = []
    for name in obj.attrs:
        try:
            size = obj.attrs.get_id(name).get_storage_size()
        except (KeyError, RuntimeError, OSError, ValueError):
            size = 0
        budget[0] -= size
        if budget[0] < 0:
            raise FormatError(f"{where}: attributes of over {MAX_ATTR_BYTES} bytes")
        try:
            v = obj.attrs[name]
        except (OSError, TypeError, ValueError, RuntimeError) as e:
            f.skipped.append(f"attribute {obj.name}@{name} ({e})")
            continue
        if isinstance(v, str):
            out.append({"name": name, "kind": "str", "value": v})
        elif isinstance(v, h5py.Empty):
            f.skipped.append(f"attribute {obj.name}@{name} (an empty value)")
        else:
            a = np.asarray(v)
            if a.dtype.kind == "O" and all(isinstance(x, str) for x in a.reshape(-1)):
                out.append({"name": name, "kind": "strs", "value": a.tolist()})
            elif a.dtype.kind in "biufS" and a.dtype.fields is None:
                key = f"attrs/{len(f.attr_arrays)}"
                f.attr_arrays[key] = a
                out.append({"name": name, "kind": "array", "key": key})
            else:
                f.skipped.append(f"attribute {obj.name}@{name} ({a.dtype} values)")
    return out


def _h5_storage(obj: Any) -> dict[str, Any]:
    return {
        "chunks": list(obj.chunks) if obj.chunks else None,
        "compression": obj.compression,
        "compression_opts": obj.compression_opts,
        "shuffle": bool(obj.shuffle) or None,
        "fletcher32": bool(obj.fletcher32) or None,
        "maxshape": list(obj.maxshape) if obj.maxshape is not None and obj.chunks else None,
    }


def _read_hdf5(fh: Any, path: Path) -> _File:
    import h5py

    what = "D4RL's .hdf5 or an .npz"
    names = hdf5_datasets(fh, path, what)
    f = _File("hdf5", path, {})
    budget = [MAX_ATTR_BYTES]
    groups: list[str] = [""]
    fh.visit(lambda n: groups.append(n) if isinstance(fh.get(n), h5py.Group) else None)
    for g in groups:
        grp = fh[g] if g else fh
        attrs = _h5_attrs(grp, f, str(path), budget)
        if attrs or (g and not len(grp)):
            f.groups.append({"name": g, "attrs": attrs})
    for name in names:
        obj = fh[name]
        if name.startswith(RLU_PREFIX):
            if obj.dtype.kind in "SUO" and h5py.check_string_dtype(obj.dtype) is not None:
                if obj.size == 1:
                    v = obj.asstr()[()]
                    f.rlu[name[len(RLU_PREFIX) :]] = v if isinstance(v, str) else str(v)
            continue
        entry: dict[str, Any] = {
            "name": name,
            "dtype": obj.dtype.str if obj.dtype.kind != "O" else None,
            "shape": list(obj.shape) if obj.shape is not None else [],
            "storage": _h5_storage(obj),
            "attrs": _h5_attrs(obj, f, str(path), budget),
        }
        info = h5py.check_string_dtype(obj.dtype)
        if obj.dtype.kind == "O" and info is not None:
            if (obj.size or 0) > MAX_STRING_VALUES:
                f.skipped.append(f"dataset {name} ({obj.size} strings)")
                continue
            try:
                v = obj.asstr()[()]
            except (OSError, ValueError, TypeError, UnicodeDecodeError) as e:
                f.skipped.append(f"dataset {name} ({e})")
                continue
            entry.update(origin="strings", value=v.tolist() if isinstance(v, np.ndarray) else v)
            entry["storage"] = {"encoding": info.encoding, "length": info.length}
        elif obj.dtype.kind in "biufS" and obj.dtype.fields is None:
            col = H5Column(obj, path, name, numeric=obj.dtype.kind != "S")
            if _want(name) and obj.dtype.kind in "biuf":
                f.cols[name] = col
            else:
                f.extra[name] = col
            entry["origin"] = "kept"
        else:
            f.skipped.append(f"dataset {name} ({obj.dtype} values)")
            continue
        f.entries.append(entry)
    return f


def _read_npz(z: NpzFile, path: Path) -> _File:
    f = _File("npz", path, {})
    for key, info in z.infos.items():
        m = z.member(key)
        if key.startswith(RLU_PREFIX):
            t = _small_text(z.column(key), str(path)) if m.dtype.kind in "SU" else None
            if t is not None:
                f.rlu[key[len(RLU_PREFIX) :]] = t
            continue
        col = z.column(key)
        if _want(key) and m.dtype.kind in "biuf":
            f.cols[key] = col
        elif m.dtype.kind in "biufSU" and m.dtype.fields is None:
            f.extra[key] = col
        else:
            f.skipped.append(f"array {key} ({m.dtype} values)")
            continue
        f.entries.append(
            {
                "name": key,
                "dtype": m.dtype.str,
                "shape": list(m.shape),
                "origin": "kept",
                "compress": info.compress_type == zipfile.ZIP_DEFLATED,
            }
        )
    return f


@contextlib.contextmanager
def _open(src: str | os.PathLike | Mapping[str, np.ndarray]) -> Iterator[_File]:
    """``src`` (a D4RL .npz or .hdf5 file, or a dict) opened for import."""
    if isinstance(src, Mapping):
        yield _File("dict", None, {k: ArrayColumn(v, k, "D4RL dict") for k, v in src.items()})
        return
    path = Path(src)
    if not path.is_file():
        raise RluError(f"{path}: no such file; give a D4RL .npz or .hdf5 file")
    if path.suffix.lower() == ".npz":
        with NpzFile(path) as z:
            yield _read_npz(z, path)
    elif path.suffix.lower() in HDF5_SUFFIXES:
        with open_hdf5(path, "D4RL's .hdf5 or an .npz") as fh:
            yield _read_hdf5(fh, path)
    else:
        raise RluError(f"{path}: unknown D4RL file type; give a .npz or .hdf5 file")


class _Source:
    """What an import keeps of a D4RL file that the store does not hold (``source/d4rl.json``
    and ``.npz``): the file's layout (array names in order, dtypes, shapes, HDF5 storage and
    attributes), its other arrays (``infos/*``, ``metadata/*``...), step arrays whose dtype the
    store's columns would change (float64 rewards), and the rows whose ``timeouts`` flag differs
    from the one export derives from the episodes (a missing timeout, a row both terminal and
    timed out)."""

    def __init__(self, f: _File, lay: _Layout, schema: Schema, folder: Path):
        from rlu.data.roundtrip import SourceWriter

        self.f, self.lay, self.schema = f, lay, schema
        self.flips: list[np.ndarray] = []
        self.folder = folder
        self._w: SourceWriter | None = None

    def on_block(
        self, a: int, terminals: np.ndarray, timeouts: np.ndarray, ends: np.ndarray
    ) -> None:
        derived = ends & ~terminals
        bad = np.flatnonzero(derived != timeouts)
        if bad.size:
            self.flips.append(bad + a)

    def _stored_dtype(self, name: str) -> np.dtype | None:
        """The dtype the store keeps step array ``name`` in (None: a flag, always exact)."""
        schema = self.schema
        top, _, key = name.partition("/")
        if name in ("terminals", "timeouts"):
            return None
        if name == "rewards":
            return np.dtype("float32")
        if name == "actions":
            return np.dtype(schema.action.dtype)
        spec = schema.observation
        if isinstance(spec, Mapping):
            if key:
                return np.dtype(spec[key].dtype) if key in spec else None
            return np.result_type(*[np.dtype(s.dtype) for s in spec.values()])
        return np.dtype(spec.dtype)

    def finish(self, w: DatasetWriter) -> None:
        import warnings

        f, src = self.f, self.w
        entries = []
        for e in f.entries:
            e = dict(e)
            name = e["name"]
            if name in f.cols:
                stored = self._stored_dtype(name)
                have = np.dtype(e["dtype"])
                lossy = stored is not None and not np.can_cast(have, stored, "safe")
                if lossy:
                    e["value"] = src.column(f"arrays/{name}", f.cols[name], str(f.path))
                    e["origin"] = "kept"
                else:
                    e["origin"] = "rows"
            elif e["origin"] == "kept":
                e["value"] = src.column(f"arrays/{name}", f.extra[name], str(f.path))
            e["dtype"] = np.dtype(e["dtype"]).str if e.get("dtype") else None
            entries.append(e)
        for key, a in f.attr_arrays.items():
            src.add(key, a)
        flips = np.concatenate(self.flips) if self.flips else np.zeros(0, np.int64)
        if flips.size:
            src.add("timeouts_flipped", flips.astype(np.int64))
        flat = None
        if "" in self.lay.obs and isinstance(self.schema.observation, Mapping):
            flat = list(flat_spec(self.schema))
        src.info.update(
            container=f.container,
            file=f.path.name if f.path else None,
            next_observations=self.lay.nxt is not None,
            flat_keys=flat,
            entries=entries,
            groups=f.groups,
            skipped=f.skipped,
        )
        src.attach(w)
        if f.skipped:
            warnings.warn(
                f"{f.path}: not kept (rlu keeps numeric arrays, strings and their attributes): "
                + "; ".join(f.skipped[:5]),
                stacklevel=3,
            )

    @property
    def w(self) -> Any:
        """The writer of ``source/``, made on first use (the destination's folder exists by
        then: the dataset writer made it)."""
        from rlu.data.roundtrip import SourceWriter

        if self._w is None:
            self._w = SourceWriter("d4rl", self.folder)
        return self._w

    def close(self) -> None:
        if self._w is not None:
            self._w.close()


def import_d4rl(
    src: str | os.PathLike | Mapping[str, np.ndarray],
    dest: str | os.PathLike,
    task_id: str | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> Path:
    """Import a D4RL-style .npz / .hdf5 file (or dict) for ``task_id`` into a new dataset at
    ``dest``. Every array's declared shape is checked against the others and the task's schema
    before a row is read; the rows are then read and written a block at a time (memory: one
    block and one episode, see rlu.data.foreign). What the store's columns do not hold is kept
    in ``source/d4rl.*`` (module docstring), so that ``export_d4rl`` gives the file back; a file
    rlu exported is restored from its sidecar (rlu.data.roundtrip). ``task_id`` may be left out
    for a file rlu exported (its task is recorded)."""
    from rlu.data.roundtrip import attach_from_sidecar, find_sidecar, restore, restored_schema
    from rlu.data.roundtrip import sidecar_path as side_of
    from rlu.tasks import get_task

    where = str(src) if not isinstance(src, Mapping) else "D4RL dict"
    dest = Path(dest)
    with _open(src) as f, contextlib.ExitStack() as stack:
        sc = None
        if f.path is not None:
            sc = find_sidecar(side_of(f.path), f.rlu.get("export_id"), where)
            if sc is not None:
                stack.callback(sc.close)
        task_id = task_id or (sc.schema.task_id if sc else None) or f.rlu.get("task_id") or None
        if not task_id:
            raise RluError(f"{where}: say which task the file holds: --task TASK")
        task = get_task(task_id)
        schema = Schema.for_task(task)
        if DOMAINS[task.domain].challenges and "observations/dummy-0" in f.cols:
            from rlu.tasks import rwrl_observation_spec

            schema = Schema.for_task(task, observation=rwrl_observation_spec(task, "easy"))
        if sc is not None:
            schema = restored_schema(sc, schema, where)
            prov: dict[str, Any] = dict(sc.info["provenance"])
        else:
            prov = {"source": "d4rl", "file": str(src) if f.path else None}
            prov.update(provenance or {})
        lay = _layout(f.cols, where)
        _check_schema(lay, schema, where)
        keep = None
        if sc is None and f.path is not None:
            keep = _Source(f, lay, schema, dest.parent)
            stack.callback(keep.close)
        segments = _iter_segments(
            lay, where, schema.frame_stack, episode_limit(task), keep.on_block if keep else None
        )

        def split(segs: Iterator[Segment]) -> Iterator[Segment]:
            for seg in segs:
                if isinstance(schema.observation, Mapping) and not isinstance(
                    seg.observation, Mapping
                ):
                    obs = split_flat(seg.observation, flat_spec(schema), f"{src}: 'observations'")
                    seg = dataclasses.replace(seg, observation=obs)
                yield seg

        segments = split(segments)
        if sc is not None:
            segments = restore(segments, sc, where)
        with DatasetWriter(dest, schema, prov) as w:
            for i, seg in enumerate(segments):
                append_checked(w, seg, schema, i, where, index_meta=sc is None)
            if sc is not None:
                attach_from_sidecar(w, sc, dest.parent)
            elif keep is not None:
                keep.finish(w)
    return dest


def append_checked(
    w: DatasetWriter, seg: Segment, schema: Schema, index: int, where: str, index_meta: bool = True
) -> None:
    """Append imported episode ``index`` of ``where`` after :func:`_cast`; the writer's own
    refusals name the source file and the episode too. ``index_meta``: record ``index`` as the
    segment's ``episode_index`` unless it has one (not for a segment restored as rlu wrote it)."""
    seg = _cast(seg, schema, index, where, index_meta)
    try:
        w.append(seg)
    except SpecError as e:
        raise SpecError(f"{where}: episode {index}: {e}") from None


def _cast(
    seg: Segment, schema: Schema, index: int, where: str = "", index_meta: bool = True
) -> Segment:
    """``seg``'s observations and actions in the schema's dtypes and shapes, refused where a
    value would not survive the cast or an action lies outside the action space."""
    where = f"{where}: episode {index}" if where else f"episode {index}"

    def cast(v: np.ndarray, spec: ArraySpec, name: str) -> np.ndarray:
        v = fits(v, spec.dtype, name, where)
        if v.ndim == 0 or v[0].size != spec.size:
            raise SpecError(
                f"{where}: {name} has per-step shape {v.shape[1:]}; the task wants {spec.shape}"
            )
        return v.reshape(len(v), *spec.shape)

    if isinstance(schema.observation, ArraySpec):
        if isinstance(seg.observation, Mapping):
            raise SpecError(f"{where}: dict observations; the task stores one array")
        obs: np.ndarray | dict[str, np.ndarray] = cast(
            seg.observation, schema.observation, "observations"
        )
    else:
        spec = schema.observation
        if not isinstance(seg.observation, Mapping):
            raise SpecError(f"{where}: one observation array; the task stores a dict")
        obs = {
            k: cast(v, spec[k], f"observations/{k}") if k in spec else v
            for k, v in seg.observation.items()
        }
    action = cast(seg.action, schema.action, "actions")
    live = ~np.asarray(seg.is_last, bool)  # a final step's action is a placeholder
    bad = action_problem(schema.action, action[live])
    if bad is not None:
        raise SpecError(f"{where}: step {int(np.flatnonzero(live)[bad[0]])}: {bad[1]}")
    meta = {"episode_index": index, **seg.metadata} if index_meta else dict(seg.metadata)
    return dataclasses.replace(seg, observation=obs, action=action, metadata=meta)


def split_flat(obs: np.ndarray, spec: Mapping[str, Any], where: str) -> dict[str, np.ndarray]:
    """(T, D) rows -> the task's observation dict, keys in spec order (D = sum of their sizes)."""
    obs = np.asarray(obs)
    sizes = [int(np.prod(s.shape, dtype=np.int64)) for s in spec.values()]
    if obs.ndim != 2 or obs.shape[1] != sum(sizes):
        raise FormatError(
            f"{where}: observations of shape {obs.shape[1:]}; the task's keys "
            f"{list(spec)} flatten to ({sum(sizes)},)"
        )
    parts = np.split(obs, np.cumsum(sizes)[:-1], axis=1)
    return {k: p.reshape(len(obs), *s.shape) for (k, s), p in zip(spec.items(), parts, strict=True)}


# --- the format registry's entry points (rlu.data.formats) ----------------------------------
def export(
    ds: Dataset, out: str | os.PathLike, *, overwrite: bool = False, note: Any = None
) -> Path:
    """``rlu export --format d4rl``: :func:`export_d4rl`."""
    return export_d4rl(ds, out, overwrite=overwrite, note=note)


def import_dataset(src: str | os.PathLike, dest: str | os.PathLike, task_id: str | None) -> Path:
    """``rlu import --format d4rl``: :func:`import_d4rl`."""
    return import_d4rl(src, dest, task_id)
