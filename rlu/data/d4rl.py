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
task id, the observation keys and sizes and the manifest's provenance (JSON); D4RL files keep
their own ``metadata/...`` the same way, and import ignores both.

``terminals[i]`` is True when transition i enters a terminal state (discount 0); ``timeouts[i]`` is
True on the last transition of every other segment (a time-limit end, or the end of a release
window), so that import cuts the rows back into the same segments.

Import cuts episodes at terminals and timeouts, and also wherever ``next_observations[i]`` differs
from ``observations[i + 1]`` (files in the wild miss some timeouts); a trailing run with neither
counts as truncated. D4RL's own .hdf5 files (flat ``observations``, ``infos/...`` and
``metadata/...`` groups, which are never read) are read as they are; those without
``next_observations`` are cut at terminals and timeouts only and read as d3rlpy reads them: after
a terminal the final observation is zeros; a timeout row (or a trailing run's last row) holds the
final observation, and its action and reward, which no transition uses, stay in the episode's
final step (d3rlpy counts that reward in the return and the returns-to-go; it used to be dropped).

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
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.episode import Segment, make_episode
from rlu.data.foreign import (
    EPISODE_LENGTH_FACTOR,
    MAX_EPISODE_BYTES,
    ArrayColumn,
    Column,
    NpzFile,
    episode_limit,
    finite_array,
    fits,
    flag_array,
    hdf5_columns,
    iter_blocks,
    open_hdf5,
    real_array,
    real_dtype,
    with_final_step,
)
from rlu.data.store import Dataset, DatasetWriter, Schema
from rlu.data.store.schema import action_problem
from rlu.data.views import TransitionView
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
        if isinstance(obs, dict):
            out.update({f"{prefix}/{k}": v for k, v in obs.items()})
        else:
            out[prefix] = obs
    out["actions"] = b.action
    out["rewards"] = b.reward
    out["terminals"] = terminals
    out["timeouts"] = last_of_segment & ~terminals
    return out


HDF5_SUFFIXES = (".hdf5", ".h5")


def d4rl_file_arrays(ds: Dataset) -> dict[str, np.ndarray]:
    """The arrays of an exported D4RL file: ``to_d4rl(ds)`` with a float dict observation
    flattened to one ``observations`` array, plus ``metadata/rlu/...`` (see the module doc)."""
    import json

    d = to_d4rl(ds)
    spec = ds.schema.observation
    meta: dict[str, np.ndarray] = {
        "metadata/rlu/task_id": np.asarray(ds.schema.task_id or ""),
        "metadata/rlu/provenance": np.asarray(json.dumps(ds.manifest.get("provenance", {}))),
    }
    if isinstance(spec, Mapping):
        keys = _flat_order(ds.schema)
        dtypes = {np.dtype(s.dtype) for s in spec.values()}
        if keys is not None and len(dtypes) == 1 and np.issubdtype(dtypes.pop(), np.floating):
            spec = {k: spec[k] for k in keys}
            meta["metadata/rlu/observation_keys"] = np.asarray(keys)
            meta["metadata/rlu/observation_sizes"] = np.asarray([s.size for s in spec.values()])
            for prefix in ("observations", "next_observations"):
                parts = [d.pop(f"{prefix}/{k}") for k in spec]
                d[prefix] = np.concatenate([p.reshape(len(p), -1) for p in parts], axis=1)
    return {**d, **meta}


def _flat_order(schema: Schema) -> list[str] | None:
    """The key order import splits a flat ``observations`` by (the task's), or None when the
    stored keys are not the task's (RWRL's extra challenge features: kept one array per key)."""
    from rlu.tasks import get_task

    try:
        task_keys = list(Schema.for_task(get_task(schema.task_id or "")).observation)
    except RluError:
        return list(schema.observation)  # no registered task: import names one; keep ours
    return task_keys if set(task_keys) == set(schema.observation) else None


def export_d4rl(ds: Dataset, out: str | os.PathLike) -> Path:
    """Write ``ds`` as a D4RL file: HDF5 for a ``.hdf5``/``.h5`` name, an .npz archive for
    ``.npz`` (see the module doc); atomically (a temp name, then rename)."""
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in (*HDF5_SUFFIXES, ".npz"):
        raise RluError(
            f"{out}: unknown D4RL file type {out.suffix or '(no extension)'!r}; name the output "
            "X.hdf5 (HDF5, D4RL's own format) or X.npz (a numpy archive)"
        )
    if suffix in HDF5_SUFFIXES:
        h5py = _require_h5py("writing D4RL .hdf5 files")
    if not out.parent.is_dir():
        raise RluError(f"{out}: the folder {out.parent} does not exist; create it first")
    from rlu.files import interrupts_deferred
    from rlu.locks import OutputLock

    arrays = d4rl_file_arrays(ds)
    tmp = out.with_name(f".{out.name}.partial{suffix}")
    with OutputLock(out, "export file"):  # one writer per output file
        try:
            if suffix == ".npz":
                np.savez(tmp, **arrays)
            else:
                f = h5py.File(tmp, "w")
                try:
                    for name, a in arrays.items():
                        if a.dtype.kind == "U":  # h5py stores str as variable-length UTF-8
                            data: Any = a.tolist()
                            f.create_dataset(name, data=data)
                        elif a.dtype == np.uint8 and a.ndim > 2:  # frames: gzip, as D4RL's
                            f.create_dataset(name, data=a, compression="gzip", compression_opts=1)
                        else:
                            f.create_dataset(name, data=a)
                finally:
                    with interrupts_deferred():  # a Ctrl-C here is raised after the close
                        f.close()
            os.replace(tmp, out)
        finally:
            tmp.unlink(missing_ok=True)
    return out


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
                f"stores its keys {list(spec)} flattened to ({size},)"
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
    lay: _Layout, where: str, frame_stack: int = 1, max_steps: int | None = None
) -> Iterator[Segment]:
    """Cut the rows into whole episodes (module docstring), reading a block of rows at a time:
    one block and one episode are held, whatever the file's length."""
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
        ends = block["terminals"] | flag_array(lay.timeouts.rows(a, b), "timeouts", where)
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
        stored = {k: v for k, v in block.items() if not k.startswith("next/")}
        s = 0
        for e in np.flatnonzero(ends).tolist():
            ep.add(a, stored, s, e + 1)
            last = {k[5:]: v[e : e + 1] for k, v in block.items() if k.startswith("next/")}
            yield _segment(*ep.take(), last, single, lay.nxt is not None, frame_stack)
            s = e + 1
        ep.add(a, stored, s, b - a)


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
    """The step arrays of a D4RL file (``infos/``, ``metadata/`` and the rest are never read)."""
    top = name.split("/", 1)[0]
    return top in ("observations", "next_observations") or name in REQUIRED


@contextlib.contextmanager
def _columns(src: str | os.PathLike | Mapping[str, np.ndarray]) -> Iterator[dict[str, Column]]:
    """The step arrays of ``src`` (a D4RL .npz or .hdf5 file, or a dict) as columns."""
    if isinstance(src, Mapping):
        yield {k: ArrayColumn(v, k, "D4RL dict") for k, v in src.items()}
        return
    path = Path(src)
    if not path.is_file():
        raise RluError(f"{path}: no such file; give a D4RL .npz or .hdf5 file")
    if path.suffix == ".npz":
        with NpzFile(path) as z:
            yield {k: z.column(k) for k in z.infos if _want(k)}
    elif path.suffix.lower() in HDF5_SUFFIXES:
        with open_hdf5(path, "D4RL's .hdf5 or an .npz") as f:
            yield hdf5_columns(f, path, _want, "D4RL's .hdf5 or an .npz")
    else:
        raise RluError(f"{path}: unknown D4RL file type; give a .npz or .hdf5 file")


def import_d4rl(
    src: str | os.PathLike | Mapping[str, np.ndarray],
    dest: str | os.PathLike,
    task_id: str,
    provenance: Mapping[str, Any] | None = None,
) -> Path:
    """Import a D4RL-style .npz / .hdf5 file (or dict) for ``task_id`` into a new dataset at
    ``dest``. Every array's declared shape is checked against the others and the task's schema
    before a row is read; the rows are then read and written a block at a time (memory: one
    block and one episode, see rlu.data.foreign)."""
    from rlu.tasks import get_task

    task = get_task(task_id)
    where = str(src) if not isinstance(src, Mapping) else "D4RL dict"
    schema = Schema.for_task(task)
    prov = {"source": "d4rl", "file": str(src) if not isinstance(src, Mapping) else None}
    prov.update(provenance or {})
    with _columns(src) as cols:
        if task.domain == "rwrl" and "observations/dummy-0" in cols:
            from rlu.tasks import rwrl_observation_spec

            schema = Schema.for_task(task, observation=rwrl_observation_spec(task, "easy"))
        lay = _layout(cols, where)
        _check_schema(lay, schema, where)
        segments = _iter_segments(lay, where, schema.frame_stack, episode_limit(task))
        with DatasetWriter(dest, schema, prov) as w:
            for i, seg in enumerate(segments):
                if isinstance(schema.observation, Mapping) and not isinstance(
                    seg.observation, Mapping
                ):
                    obs = split_flat(seg.observation, schema.observation, f"{src}: 'observations'")
                    seg = dataclasses.replace(seg, observation=obs)
                append_checked(w, seg, schema, i, where)
    return Path(dest)


def append_checked(w: DatasetWriter, seg: Segment, schema: Schema, index: int, where: str) -> None:
    """Append imported episode ``index`` of ``where`` after :func:`_cast`; the writer's own
    refusals name the source file and the episode too."""
    seg = _cast(seg, schema, index, where)
    try:
        w.append(seg)
    except SpecError as e:
        raise SpecError(f"{where}: episode {index}: {e}") from None


def _cast(seg: Segment, schema: Schema, index: int, where: str = "") -> Segment:
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
        obs = cast(seg.observation, schema.observation, "observations")
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
    meta = {**seg.metadata, "episode_index": index}
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
