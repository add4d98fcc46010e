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
``metadata/...`` groups, which are ignored) are read as they are; those without
``next_observations`` are cut at terminals and timeouts only (see ``_segments_without_next``).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.episode import Segment, make_episode
from rlu.data.foreign import (
    finite_array,
    fits,
    flag_array,
    read_hdf5,
    read_npz,
    real_array,
    rows,
)
from rlu.data.store import Dataset, DatasetWriter, Schema
from rlu.data.store.schema import action_problem
from rlu.data.views import TransitionView
from rlu.types import ArraySpec, FormatError, RluError, SpecError, install_hint

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
    arrays = d4rl_file_arrays(ds)
    tmp = out.with_name(f".{out.name}.partial{suffix}")
    try:
        if suffix == ".npz":
            np.savez(tmp, **arrays)
        else:
            with h5py.File(tmp, "w") as f:
                for name, a in arrays.items():
                    if a.dtype.kind == "U":  # h5py stores str as variable-length UTF-8
                        data: Any = a.tolist()
                        f.create_dataset(name, data=data)
                    elif a.dtype == np.uint8 and a.ndim > 2:  # frames: gzip, as D4RL's own files
                        f.create_dataset(name, data=a, compression="gzip", compression_opts=1)
                    else:
                        f.create_dataset(name, data=a)
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


def _split_obs(d: Mapping[str, np.ndarray], prefix: str, n: int, where: str) -> Any:
    """The ``prefix`` observations (one array, or ``prefix/<key>`` arrays), one real row per
    step."""
    if prefix in d:
        return rows(real_array(d[prefix], prefix, where), prefix, where, n)
    keys = {k[len(prefix) + 1 :]: k for k in d if k.startswith(prefix + "/")}
    if not keys:
        raise FormatError(f"{where}: no {prefix!r} array and no '{prefix}/<key>' arrays")
    return {k: rows(real_array(d[full], full, where), full, where, n) for k, full in keys.items()}


def _rows(obs: Any, sl: slice | np.ndarray) -> Any:
    if isinstance(obs, dict):
        return {k: v[sl] for k, v in obs.items()}
    return obs[sl]


def _step_columns(d: Mapping[str, np.ndarray], where: str) -> tuple[np.ndarray, ...]:
    """actions, rewards, terminals, timeouts of a D4RL dict: real numbers, finite rewards, flags
    of 0 or 1, one row each (at least one)."""
    rewards = finite_array(d["rewards"], "rewards", where)
    if rewards.ndim == 2 and rewards.shape[1] == 1:
        rewards = rewards[:, 0]  # (n, 1), as d3rlpy and some D4RL copies store them
    if rewards.ndim != 1:
        raise FormatError(f"{where}: 'rewards' has shape {rewards.shape}; one reward per row")
    n = len(rewards)
    if n == 0:
        raise FormatError(f"{where}: 'rewards' has no rows; there is nothing to import")
    actions = rows(real_array(d["actions"], "actions", where), "actions", where, n)
    terminals = rows(flag_array(d["terminals"], "terminals", where), "terminals", where, n)
    timeouts = rows(flag_array(d["timeouts"], "timeouts", where), "timeouts", where, n)
    return actions, rewards, terminals, timeouts


def d4rl_segments(
    d: Mapping[str, np.ndarray], frame_stack: int = 1, where: str = "D4RL dict"
) -> list[Segment]:
    """Cut a D4RL-style dict into whole episodes (see the module docstring)."""
    missing = [k for k in REQUIRED if k not in d]
    if missing:
        raise FormatError(
            f"{where}: missing array(s) {missing}; a D4RL dict has {', '.join(REQUIRED)}"
        )
    actions, rewards, terminals, timeouts = _step_columns(d, where)
    n = len(rewards)
    obs = _split_obs(d, "observations", n, where)
    if "next_observations" not in d and not any(k.startswith("next_observations/") for k in d):
        return _segments_without_next(obs, actions, rewards, terminals, timeouts, frame_stack)
    nxt = _split_obs(d, "next_observations", n, where)
    if isinstance(obs, dict) != isinstance(nxt, dict) or (
        isinstance(obs, dict) and set(obs) != set(nxt)
    ):
        raise FormatError(f"{where}: 'observations' and 'next_observations' differ in their keys")
    pairs = [(obs[k], nxt[k]) for k in obs] if isinstance(obs, dict) else [(obs, nxt)]
    if any(a.shape != b.shape for a, b in pairs):
        raise FormatError(f"{where}: 'observations' and 'next_observations' differ in shape")
    ends = terminals | timeouts
    if n > 1:
        # a row whose successor does not continue from its next observation ends an episode
        if isinstance(obs, dict):
            cont = np.ones(n - 1, bool)
            for k in obs:
                a, b = nxt[k][:-1].reshape(n - 1, -1), obs[k][1:].reshape(n - 1, -1)
                cont &= (a == b).all(axis=1)
        else:
            cont = (nxt[:-1].reshape(n - 1, -1) == obs[1:].reshape(n - 1, -1)).all(axis=1)
        ends[:-1] |= ~cont
    if n:
        ends[-1] = True
    stops = np.flatnonzero(ends) + 1
    starts = np.concatenate([[0], stops[:-1]])
    segments = []
    for a, b in zip(starts.tolist(), stops.tolist(), strict=True):
        o = _rows(obs, slice(a, b))
        last_next = _rows(nxt, slice(b - 1, b))
        if isinstance(o, dict):
            ep_obs = {k: np.concatenate([o[k], last_next[k]]) for k in o}
        else:
            ep_obs = np.concatenate([o, last_next])
        prefix = None
        if frame_stack > 1:  # stacked Atari observations -> frames stored once
            if isinstance(ep_obs, dict) or ep_obs.ndim < 2 or ep_obs.shape[-1] != frame_stack:
                raise FormatError(
                    f"{where}: frame-stacked import needs one 'observations' array of stacks "
                    f"(..., {frame_stack}), newest frame last"
                )
            prefix = np.moveaxis(ep_obs[0, ..., : frame_stack - 1], -1, 0)
            ep_obs = ep_obs[..., -1]
        segments.append(
            make_episode(
                ep_obs, actions[a:b], rewards[a:b], bool(terminals[b - 1]), frame_prefix=prefix
            )
        )
    return segments


def _segments_without_next(
    obs: Any,
    actions: np.ndarray,
    rewards: np.ndarray,
    terminals: np.ndarray,
    timeouts: np.ndarray,
    frame_stack: int,
) -> list[Segment]:
    """Files without ``next_observations`` (several of D4RL's, AntMaze among them): cut at
    terminals and timeouts only, and read as d3rlpy does: after a terminal the final observation is
    zeros;
    a timeout row (or a trailing run) holds the final observation, its action and reward unused."""
    n = len(rewards)
    if frame_stack > 1:
        raise FormatError("frame-stacked import needs 'next_observations'")
    ends = terminals | timeouts
    if n:
        ends[-1] = True
    stops = np.flatnonzero(ends) + 1
    starts = np.concatenate([[0], stops[:-1]])
    segments = []
    for a, b in zip(starts.tolist(), stops.tolist(), strict=True):
        o = _rows(obs, slice(a, b))
        if terminals[b - 1]:
            if isinstance(o, dict):
                o = {k: np.concatenate([v, np.zeros_like(v[:1])]) for k, v in o.items()}
            else:
                o = np.concatenate([o, np.zeros_like(o[:1])])
            segments.append(make_episode(o, actions[a:b], rewards[a:b], True))
        else:
            segments.append(make_episode(o, actions[a : b - 1], rewards[a : b - 1], False))
    return segments


def import_d4rl(
    src: str | os.PathLike | Mapping[str, np.ndarray],
    dest: str | os.PathLike,
    task_id: str,
    provenance: Mapping[str, Any] | None = None,
) -> Path:
    """Import a D4RL-style .npz (or dict) for ``task_id`` into a new dataset at ``dest``."""
    from rlu.tasks import get_task

    task = get_task(task_id)
    if isinstance(src, (str, os.PathLike)):
        path = Path(src)
        if not path.is_file():
            raise RluError(f"{path}: no such file; give a D4RL .npz or .hdf5 file")
        if path.suffix == ".npz":
            data = _read_npz(path)
        elif path.suffix.lower() in HDF5_SUFFIXES:
            data = _read_hdf5(path)
        else:
            raise RluError(f"{path}: unknown D4RL file type; give a .npz or .hdf5 file")
    else:
        data = dict(src)
    where = str(src) if not isinstance(src, Mapping) else "D4RL dict"
    schema = Schema.for_task(task)
    if task.domain == "rwrl" and "observations/dummy-0" in data:
        from rlu.tasks import rwrl_observation_spec

        schema = Schema.for_task(task, observation=rwrl_observation_spec(task, "easy"))
    segments = d4rl_segments(data, frame_stack=schema.frame_stack, where=where)
    prov = {"source": "d4rl", "file": str(src) if not isinstance(src, Mapping) else None}
    prov.update(provenance or {})
    with DatasetWriter(dest, schema, prov) as w:
        for i, seg in enumerate(segments):
            if isinstance(schema.observation, Mapping) and not isinstance(seg.observation, Mapping):
                obs = split_flat(seg.observation, schema.observation, f"{src}: 'observations'")
                seg = dataclasses.replace(seg, observation=obs)
            append_checked(w, seg, schema, i, where)
    return Path(dest)


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an .npz file; object arrays (pickles) are refused, never unpickled."""
    return read_npz(path)


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


def _read_hdf5(path: Path) -> dict[str, np.ndarray]:
    """The step arrays of a D4RL .hdf5 file (``infos/`` and ``metadata/`` are never read)."""

    def want(name: str) -> bool:
        top = name.split("/", 1)[0]
        return top in ("observations", "next_observations") or name in REQUIRED

    return read_hdf5(path, want, "D4RL's .hdf5 or an .npz")
