"""d3rlpy's dataset dump (``MDPDataset.dump`` / ``ReplayBuffer.dump``, format 2.1), in and out.

The dump is an HDF5 file written by ``d3rlpy.dataset.io.dump``: ``version`` ("2.1"),
``columns`` (the episode fields: ``observations, actions, rewards, terminated``),
``num_episodes`` and, per episode i, ``observations_<i>`` (or ``observations_<i>_<j>`` for tuple
observations), ``actions_<i>``, ``rewards_<i>`` (T, 1) and ``terminated_<i>``. It is read with
h5py only (no d3rlpy needed, nothing unpickled).

d3rlpy's episodes are already cut (at ``terminals`` and ``timeouts`` when the MDPDataset was
built). An episode of T rows maps onto rlu's step semantics exactly as d3rlpy's own
``BasicTransitionPicker`` reads it:

- terminated: T transitions; the final observation is zeros (d3rlpy's next observation after a
  terminal), discount 0 on the last transition;
- not terminated (a timeout): T - 1 transitions; the last row's observation is the final
  observation, and its action (d3rlpy's ``next_action`` of the last transition) and reward (no
  transition's, but part of d3rlpy's return and returns-to-go) are kept in the final step.

The file is read warily (rlu.data.foreign): its links and storage are checked before anything is
read (no soft or external links, no values stored outside the file), and each episode's arrays
are checked against each other and the task's schema, and bounded, before they are read.

``export_d3rlpy`` writes the same layout back (d3rlpy's own ``ReplayBuffer.load`` reads it); a
dump imported and exported again holds the same arrays.

Atari dumps come in two layouts, both stored back as single frames:

- d3rlpy's default, single frames (``d3rlpy.datasets.get_atari(..., pre_stack=False)``): rows of
  (1, 84, 84) uint8, channel first (or (84, 84)), stacked at sampling time by d3rlpy's
  ``FrameStackTransitionPicker``, which pads the frames before an episode's first with zeros:
  rlu stores the frames once with a zero frame prefix, and its views stack the same
  observations;
- pre-stacked rows ((k, 84, 84) channel first or (84, 84, k)): consecutive rows must share
  frames, and the first row's older frames become the frame prefix.

After a terminal d3rlpy's next observation is all zeros; rlu's is the stack ending in a zero
frame (its k - 1 older frames are the episode's last ones). Both are multiplied by discount 0.
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

from rlu.data.foreign import (
    EPISODE_LENGTH_FACTOR,
    MAX_EPISODE_BYTES,
    Column,
    H5Column,
    episode_limit,
    finite_array,
    flag_array,
    h5_array,
    h5_check,
    open_hdf5,
    real_array,
    with_final_step,
)
from rlu.data.store import Dataset, DatasetWriter, Schema
from rlu.segments import Segment, make_episode
from rlu.types import ArraySpec, DiscreteSpec, FormatError, RluError

SUPPORTED_VERSIONS = ("2.1",)


def d3rlpy_segments(
    path: str | os.PathLike, schema: Schema | None = None, max_steps: int | None = None
) -> Iterator[Segment]:
    """The episodes of a d3rlpy dump as whole-episode segments (see the module docstring).

    Each episode's arrays are checked before they are read: one row count, per-row sizes that
    ``schema`` can store (when given), at most ``max_steps`` transitions and
    ``MAX_EPISODE_BYTES`` in all (rlu.data.foreign)."""
    path = Path(path)
    if not path.is_file():
        raise RluError(f"{path}: no such file; give a file from d3rlpy's dump()")
    with open_hdf5(path, "a file from d3rlpy's dump()") as f:
        yield from _dump_segments(f, path, schema, max_steps)


def _num_episodes(f: Any, path: Path) -> int:
    for key in ("version", "columns", "num_episodes"):
        if key not in f:
            raise FormatError(
                f"{path}: no {key!r} entry; not a d3rlpy dump (MDPDataset.dump writes "
                "version, columns, num_episodes)"
            )
    version = _small(f, "version", path)
    version = version.decode() if isinstance(version, bytes) else str(version)
    if version not in SUPPORTED_VERSIONS:
        raise FormatError(
            f"{path}: field 'version' is {version!r}; rlu reads d3rlpy dump version(s) "
            f"{SUPPORTED_VERSIONS}: re-dump with d3rlpy >= 2.1"
        )
    raw_columns = _small(f, "columns", path)
    columns = [c.decode() if isinstance(c, bytes) else str(c) for c in np.ravel(raw_columns)]
    for need in ("observations", "actions", "rewards", "terminated"):
        if need not in columns:
            raise FormatError(f"{path}: column {need!r} missing from 'columns' {columns}")
    num = np.asarray(h5_array(f["num_episodes"], path, "num_episodes", max_bytes=8))
    if num.size != 1 or num.dtype.kind not in "iu" or not 0 <= int(num.reshape(())) < 1 << 40:
        raise FormatError(f"{path}: 'num_episodes' is {num!r}; a count of episodes")
    return int(num.reshape(()))


def _dump_segments(
    f: Any, path: Path, schema: Schema | None = None, max_steps: int | None = None
) -> Iterator[Segment]:
    for i in range(_num_episodes(f, path)):
        yield _episode(f, i, path, schema, max_steps)


def _small(f: Any, key: str, path: Path) -> Any:
    """A header entry (version, columns) of a few values, checked before it is read."""
    import h5py

    obj = f[key]
    if not isinstance(obj, h5py.Dataset) or obj.size is None or obj.size > 64:
        raise FormatError(f"{path}: entry {key!r} is not a short list; not a d3rlpy dump")
    h5_check(obj, path, key, numeric=False)
    try:
        return obj[()]
    except (OSError, ValueError, TypeError) as e:
        raise FormatError(f"{path}: entry {key!r} cannot be read ({e})") from None


def _columns(f: Any, key: str, i: int, path: Path) -> list[Column]:
    """Episode ``i``'s ``key`` entry (or its tuple parts ``key_i_j``), not yet read."""
    name = f"{key}_{i}"
    if name in f:
        return [H5Column(f[name], path, name)]
    parts: list[Column] = []
    while f"{name}_{len(parts)}" in f:
        part = f"{name}_{len(parts)}"
        parts.append(H5Column(f[part], path, part))
    if not parts:
        raise FormatError(f"{path}: episode {i} has no {name!r} entry")
    return parts


def _check_episode(
    obs: list[Column],
    actions: Column,
    rewards: Column,
    where: str,
    schema: Schema | None,
    max_steps: int | None,
) -> None:
    """Row counts, per-row sizes and the episode's size, as declared (nothing read yet)."""
    t = rewards.shape[0] if rewards.shape else 0
    counts = [c.shape[0] if c.shape else None for c in (*obs, actions)]
    if (
        len(rewards.shape) not in (1, 2)
        or math.prod(rewards.shape[1:]) != 1
        or any(c != t for c in counts)
    ):
        raise FormatError(
            f"{where}: {[c.shape[:1] for c in obs]} observations, {actions.shape[:1]} actions, "
            f"{rewards.shape[:1]} rewards; want one of each per step"
        )
    if t == 0:
        raise FormatError(f"{where}: the episode is empty")
    if max_steps is not None and t > max_steps + 1:
        raise FormatError(
            f"{where}: {t} rows, more than {max_steps + 1} ({EPISODE_LENGTH_FACTOR} times its "
            "task's episode length); the file is damaged or not what it claims"
        )
    size = sum(c.nbytes for c in (*obs, actions, rewards))
    if size > MAX_EPISODE_BYTES:
        raise FormatError(
            f"{where}: the episode declares {size} bytes, more than the {MAX_EPISODE_BYTES} one "
            "episode may hold; the file is damaged or not what it claims"
        )
    if schema is None:
        return
    task = schema.task_id or "the schema"
    if math.prod(actions.shape[1:]) != schema.action.size:
        raise FormatError(
            f"{where}: 'actions' has rows of shape {actions.shape[1:]}; task {task} stores "
            f"{schema.action.shape}"
        )
    spec = schema.observation
    have = [math.prod(c.shape[1:]) for c in obs]
    if isinstance(spec, ArraySpec):
        sizes = [[spec.size]] + (
            [[spec.size * schema.frame_stack]] if schema.frame_stack > 1 else []
        )
        want = f"{spec.shape}" + (
            f" frames (or stacks of {schema.frame_stack})" if schema.frame_stack > 1 else ""
        )
    else:
        from rlu.data.d4rl import flat_spec

        ordered = flat_spec(schema)
        sizes = [[sum(s.size for s in ordered.values())], [s.size for s in ordered.values()]]
        want = f"{list(ordered)} flattened or as a tuple, in that order"
    if have not in sizes:
        raise FormatError(
            f"{where}: observations of {[c.shape[1:] for c in obs]} per row; task {task} stores "
            f"{want}"
        )


def _episode(
    f: Any, i: int, path: Path, schema: Schema | None = None, max_steps: int | None = None
) -> Segment:
    where = f"{path}: episode {i}"
    obs_cols = _columns(f, "observations", i, path)
    (act_col,) = _one(_columns(f, "actions", i, path), where, "actions")
    (rew_col,) = _one(_columns(f, "rewards", i, path), where, "rewards")
    (term_col,) = _one(_columns(f, "terminated", i, path), where, "terminated")
    if math.prod(term_col.shape) != 1:
        raise FormatError(
            f"{where}: 'terminated' holds {math.prod(term_col.shape)} values; want one"
        )
    terminated = bool(flag_array(term_col.read(), "terminated", where)[0])
    _check_episode(obs_cols, act_col, rew_col, where, schema, max_steps)
    parts = [real_array(c.read(), "observations", where) for c in obs_cols]
    if len(parts) > 1:
        if schema is None or not isinstance(schema.observation, Mapping):
            raise FormatError(f"{where}: tuple observations; the task stores one array")
        from rlu.data.d4rl import flat_spec

        obs: Any = {k: p for k, p in zip(flat_spec(schema), parts, strict=True)}
    else:
        obs = parts[0]
    actions = real_array(act_col.read(), "actions", where)
    rewards = finite_array(rew_col.read(), "rewards", where).reshape(-1)
    if terminated:
        final = {k: np.zeros_like(v[:1]) for k, v in obs.items()} if len(parts) > 1 else None
        if final is not None:
            return make_episode(
                {k: np.concatenate([v, final[k]]) for k, v in obs.items()}, actions, rewards, True
            )
        return make_episode(np.concatenate([obs, np.zeros_like(obs[:1])]), actions, rewards, True)
    seg = make_episode(obs, actions[:-1], rewards[:-1], False)
    return with_final_step(seg, actions[-1], float(rewards[-1]))


def _one(cols: list[Column], where: str, key: str) -> list[Column]:
    if len(cols) != 1:
        raise FormatError(f"{where}: {key!r} is a tuple of {len(cols)} arrays; want one array")
    return cols


def import_d3rlpy(
    src: str | os.PathLike,
    dest: str | os.PathLike,
    task_id: str | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> Path:
    """Import a d3rlpy dump (.h5) for ``task_id`` into a new dataset at ``dest``.

    d3rlpy holds one observation array (or a tuple of them): for a task with dict observations
    one array is split into the task's keys in the task's key order (dm_control's
    ``flatten_observation`` layout), a tuple holds one array per key in that order. Atari dumps
    hold single frames (d3rlpy's default) or stacked ones (see the module docstring); both are
    stored back as single frames. What the store's columns do not hold (the dump's dtypes and
    row shapes, arrays whose dtype the store would change, other entries) is kept in
    ``source/d3rlpy.*`` so that ``export_d3rlpy`` gives the dump back; a dump rlu exported is
    restored from its sidecar (rlu.data.roundtrip). ``task_id`` may be left out for a dump rlu
    exported.
    """
    from rlu.data.d4rl import append_checked, flat_spec, split_flat
    from rlu.data.roundtrip import (
        attach_from_sidecar,
        find_sidecar,
        restore,
        restored_schema,
        sidecar_path,
    )
    from rlu.tasks import get_task

    path, dest = Path(src), Path(dest)
    if not path.is_file():
        raise RluError(f"{path}: no such file; give a file from d3rlpy's dump()")
    where = str(src)
    with open_hdf5(path, "a file from d3rlpy's dump()") as f, contextlib.ExitStack() as stack:
        mark = {k: _attr_text(f, k) for k in ("rlu_export_id", "rlu_task_id")}
        sc = find_sidecar(sidecar_path(path), mark["rlu_export_id"], where)
        if sc is not None:
            stack.callback(sc.close)
        task_id = task_id or (sc.schema.task_id if sc else None) or mark["rlu_task_id"]
        if not task_id:
            raise RluError(f"{where}: say which task the dump holds: --task TASK")
        task = get_task(task_id)
        schema = Schema.for_task(task)
        if sc is not None:
            schema = restored_schema(sc, schema, where)
            prov: dict[str, Any] = dict(sc.info["provenance"])
        else:
            prov = {"source": "d3rlpy", "file": str(src)}
            prov.update(provenance or {})
        keep = None if sc is not None else _Source(f, path, schema, dest.parent)
        if keep is not None:
            stack.callback(keep.close)

        def segments() -> Iterator[Segment]:
            for i, seg in enumerate(_dump_segments(f, path, schema, episode_limit(task))):
                if isinstance(schema.observation, Mapping) and not isinstance(
                    seg.observation, Mapping
                ):
                    obs = split_flat(seg.observation, flat_spec(schema), where)
                    seg = dataclasses.replace(seg, observation=obs)
                if schema.frame_stack > 1 and isinstance(schema.observation, ArraySpec):
                    frame = schema.observation.shape  # one frame; the store keeps k
                    seg = _unstack_segment(seg, schema.frame_stack, f"{src}: episode {i}", frame)
                yield seg

        segs: Iterator[Segment] = segments()
        if sc is not None:
            segs = restore(segs, sc, where)
        with DatasetWriter(dest, schema, prov) as w:
            for i, seg in enumerate(segs):
                append_checked(w, seg, schema, i, where, index_meta=sc is None)
            if sc is not None:
                attach_from_sidecar(w, sc, dest.parent)
            elif keep is not None:
                keep.finish(w)
    return dest


def _attr_text(f: Any, key: str) -> str | None:
    """A short text attribute of the file's root (rlu's mark), or None."""
    if key not in f.attrs:
        return None
    try:
        v = f.attrs[key]
    except (OSError, TypeError, ValueError):
        return None
    v = v.decode("utf-8", "replace") if isinstance(v, bytes) else v
    return v if isinstance(v, str) and len(v) <= 256 else None


_KINDS = ("observations", "actions", "rewards", "terminated")
_HEADER = ("columns", "num_episodes", "version")


class _Source:
    """What an import keeps of a d3rlpy dump (``source/d3rlpy.*``): each column's dtype and row
    shape (one per column, as d3rlpy writes them), the columns whose dtype the store would
    change (all episodes' rows, concatenated), other numeric entries and the root's attributes.
    Only metadata is read here; kept columns are copied after the episodes are written."""

    def __init__(self, f: Any, path: Path, schema: Schema, folder: Path):
        from rlu.data.roundtrip import SourceWriter

        self.f, self.path, self.schema = f, path, schema
        self.n = _num_episodes(f, path)
        self.layout: dict[str, Any] | None = None
        self.skipped: list[str] = []
        cols = {k: [_columns(f, k, i, path) for i in range(self.n)] for k in _KINDS}
        layout: dict[str, Any] = {}
        for kind, per in cols.items():
            first = [(c.dtype.name, list(c.shape[1:] if kind != "terminated" else c.shape))
                     for c in per[0]] if per else []  # fmt: skip
            for i, ep in enumerate(per):
                here = [(c.dtype.name, list(c.shape[1:] if kind != "terminated" else c.shape))
                        for c in ep]  # fmt: skip
                if here != first:
                    self.skipped.append(f"{kind} of episode {i} differ from episode 0's")
            layout[kind] = [{"dtype": d, "row_shape": s} for d, s in first]
        self.cols = cols
        named = {f"{k}_{i}" for k in _KINDS for i in range(self.n)}
        parts = {c.name for per in cols.values() for ep in per for c in ep}
        self.others = [n for n in f if n not in _HEADER and n not in named | parts]
        self.layout = None if self.skipped else layout
        self.folder = folder
        self._w: SourceWriter | None = None

    def _stored(self, kind: str, layout: Mapping[str, Any]) -> list[np.dtype | None]:
        s = self.schema
        if kind == "terminated":
            return [None]
        if kind == "rewards":
            return [np.dtype("float32")]
        if kind == "actions":
            return [np.dtype(s.action.dtype)]
        spec = s.observation
        if isinstance(spec, Mapping):
            return [np.result_type(*[np.dtype(v.dtype) for v in spec.values()])] * len(
                layout["observations"]
            )
        return [np.dtype(spec.dtype)]

    def finish(self, w: DatasetWriter) -> None:
        import warnings

        from rlu.data.foreign import H5Column

        src = self.w
        if self.layout is not None:
            for kind, parts in self.layout.items():
                stored_dtypes = self._stored(kind, self.layout)
                for j, (part, stored) in enumerate(zip(parts, stored_dtypes, strict=False)):
                    have = np.dtype(part["dtype"])
                    if stored is not None and not np.can_cast(have, stored, "safe"):
                        part["kept"] = self._concat(f"kept/{kind}_{j}", kind, j)
        others = []
        for name in self.others:
            obj = self.f[name]
            if getattr(obj, "dtype", None) is not None and obj.dtype.kind in "biufS":
                col = H5Column(obj, self.path, name, numeric=obj.dtype.kind != "S")
                others.append({"name": name, "key": src.column(f"others/{name}", col, "")})
            else:
                self.skipped.append(f"entry {name}")
        attrs = {}
        for k in self.f.attrs:
            v = self.f.attrs[k]
            if isinstance(v, str):
                attrs[k] = {"kind": "str", "value": v}
            elif np.asarray(v).dtype.kind in "biuf":
                attrs[k] = {"kind": "array", "key": src.add(f"attrs/{k}", np.asarray(v))}
            else:
                self.skipped.append(f"attribute {k}")
        src.info.update(
            file=self.path.name, layout=self.layout, others=others, attrs=attrs,
            skipped=self.skipped,
        )  # fmt: skip
        src.attach(w)
        if self.skipped:
            warnings.warn(
                f"{self.path}: not kept: {'; '.join(self.skipped[:5])}; an export writes "
                "d3rlpy's default layout instead",
                stacklevel=3,
            )

    def _concat(self, key: str, kind: str, j: int) -> str:
        per = [ep[j] for ep in self.cols[kind]]
        rows = sum(c.shape[0] if c.shape else 1 for c in per)
        shape = (rows, *per[0].shape[1:]) if kind != "terminated" else (rows,)
        with self.w.npz.member(key, shape, per[0].dtype) as write:
            for c in per:
                write(c.read().reshape(-1, *shape[1:]))
        self.w.info["arrays"][key] = {"shape": list(shape), "dtype": per[0].dtype.name}
        return key

    @property
    def w(self) -> Any:
        """The writer of ``source/``, made on first use (the destination's folder exists by
        then: the dataset writer made it)."""
        from rlu.data.roundtrip import SourceWriter

        if self._w is None:
            self._w = SourceWriter("d3rlpy", self.folder)
        return self._w

    def close(self) -> None:
        if self._w is not None:
            self._w.close()


def _unstack_segment(seg: Segment, k: int, where: str, frame: tuple[int, ...]) -> Segment:
    from rlu.data.minari import _unstack

    obs = np.asarray(seg.observation)
    if obs.shape[1:] in ((1, *frame), frame):  # d3rlpy's single frames, stacked when sampled
        frames = obs.reshape(len(obs), *frame)
        prefix = np.zeros((k - 1, *frame), frames.dtype)  # FrameStackTransitionPicker's padding
        return dataclasses.replace(seg, observation=frames, frame_prefix=prefix)
    if obs.ndim >= 2 and obs.shape[1] == k and obs.shape[-1] != k:  # d3rlpy's channel-first stack
        obs = np.moveaxis(obs, 1, -1)
    if seg.is_terminal[-1]:  # the zero final observation is not a stack of the episode's frames
        frames, prefix = _unstack(obs[:-1], k, where)
        frames = np.concatenate([frames, np.zeros_like(frames[:1])])
    else:
        frames, prefix = _unstack(obs, k, where)
    return dataclasses.replace(seg, observation=frames, frame_prefix=prefix)


# --- export ---------------------------------------------------------------------------------------
def _default_layout(schema: Schema) -> dict[str, Any]:
    """The columns' dtypes and row shapes of rlu's d3rlpy dumps (``export_d3rlpy``)."""
    from rlu.data.d4rl import _flat_keys, _flat_order

    spec = schema.observation
    if schema.frame_stack > 1 and isinstance(spec, ArraySpec):  # d3rlpy's Atari layout:
        # single frames, channel first
        obs = [{"dtype": spec.dtype, "row_shape": [1, *spec.shape]}]
    elif isinstance(spec, Mapping):
        flat = _flat_keys(schema)
        if flat is not None:
            size = sum(spec[k].size for k in flat)
            obs = [{"dtype": spec[flat[0]].dtype, "row_shape": [size]}]
        else:
            keys = _flat_order(schema) or list(spec)
            obs = [{"dtype": spec[k].dtype, "row_shape": list(spec[k].shape)} for k in keys]
    else:
        obs = [{"dtype": spec.dtype, "row_shape": list(spec.shape)}]
    act = schema.action
    if isinstance(act, DiscreteSpec):
        actions = [{"dtype": "int64", "row_shape": [1]}]
    else:
        actions = [{"dtype": act.dtype, "row_shape": list(act.shape)}]
    return {
        "observations": obs,
        "actions": actions,
        "rewards": [{"dtype": "float32", "row_shape": [1]}],
        "terminated": [{"dtype": "bool", "row_shape": []}],
    }


def d3rlpy_episodes(
    ds: Dataset, layout: Mapping[str, Any] | None = None
) -> Iterator[tuple[int, dict[str, Any]]]:
    """(segment index, the arrays of one d3rlpy episode) for every segment with a transition, as
    ``d3rlpy.dataset.Episode.serialize`` holds them, in ``layout`` (the columns' dtypes and row
    shapes: rlu's default, or those of the dump the dataset was imported from)."""
    from rlu.data.d4rl import _flat_order
    from rlu.data.views import DatasetView

    schema = ds.schema
    layout = layout or _default_layout(schema)
    spec = schema.observation
    keys = (_flat_order(schema) or list(spec)) if isinstance(spec, Mapping) else None
    obs_parts = layout["observations"]
    view = DatasetView(ds)
    k = schema.frame_stack
    from rlu.data.roundtrip import release_all

    read = 0
    for i in range(len(ds)):
        if ds.length[i] < 2:
            continue
        seg = ds.segment(i)
        read += int(ds.length[i])
        if read > 1 << 16:  # the pages read so far go back (rlu.data.roundtrip.release_all)
            release_all(ds)
            read = 0
        terminal = bool(seg.is_terminal[-1])
        t = len(seg) - 1 if terminal else len(seg)  # d3rlpy keeps no state after a terminal
        if keys is not None:
            parts = [np.asarray(seg.observation[key][:t]).reshape(t, -1) for key in keys]
            if len(obs_parts) == 1:
                obs: Any = np.concatenate(parts, axis=1)
            else:
                obs = [np.asarray(seg.observation[key][:t]) for key in keys]
        elif k > 1:
            assert isinstance(spec, ArraySpec) and not isinstance(seg.observation, Mapping)
            row = tuple(obs_parts[0]["row_shape"])
            if row in ((1, *spec.shape), tuple(spec.shape)):
                obs = np.asarray(seg.observation[:t])
            else:  # pre-stacked rows: the stacks rlu's views make
                steps = ds.start[i] + np.arange(t)
                obs = view.observation(np.full(t, i), steps)
                if row[0] == k and row[-1] != k:
                    obs = np.moveaxis(obs, -1, 1)
        else:
            assert not isinstance(seg.observation, Mapping)  # keys is None
            obs = np.asarray(seg.observation[:t])
        if not isinstance(obs, list):
            obs = [obs]
        obs = [
            np.asarray(o).astype(p["dtype"], copy=False).reshape(t, *p["row_shape"])
            for o, p in zip(obs, obs_parts, strict=True)
        ]
        a, r, d = (layout[x][0] for x in ("actions", "rewards", "terminated"))
        yield (
            i,
            {
                "observations": obs[0] if len(obs) == 1 else obs,
                "actions": np.asarray(seg.action[:t])
                .astype(a["dtype"])
                .reshape(t, *a["row_shape"]),
                "rewards": np.asarray(seg.reward[:t])
                .astype(r["dtype"])
                .reshape(t, *r["row_shape"]),
                "terminated": np.asarray(terminal).astype(d["dtype"]).reshape(d["row_shape"]),
            },
        )


def _rows(x: Any, part: Mapping[str, Any], t: int) -> np.ndarray:
    return np.asarray(x).astype(part["dtype"], copy=False).reshape(t, *part["row_shape"])


def is_rlu_d3rlpy(path: Path) -> bool:
    """Whether ``path`` is a d3rlpy dump rlu wrote (its root carries ``rlu_task_id``)."""
    try:
        f = open_hdf5(path, "a d3rlpy dump rlu wrote")
    except (RluError, OSError):
        return False
    try:
        return "rlu_task_id" in f.attrs or "rlu_export_id" in f.attrs
    finally:
        f.close()


def _write_episodes(h5: Any, ds: Dataset, keys: list[str], layout: Any, source: Any) -> int:
    """Every d3rlpy episode of ``ds`` into the open dump ``h5`` (``<key>_<j>``, or
    ``<key>_<j>_<n>`` for a tuple observation's parts), columns an import kept in their own
    dtypes and shapes; returns how many."""
    kept = _kept_columns(source, layout)
    written = 0
    for j, (_, ep) in enumerate(d3rlpy_episodes(ds, layout)):
        for key in keys:
            value = ep[key]
            parts = value if isinstance(value, list) else [value]
            for n, part in enumerate(parts):
                if (key, n) in kept:
                    part = kept[(key, n)].take(len(part) if key != "terminated" else 1)
                    part = part.reshape(np.shape(value if len(parts) == 1 else part))
                name = f"{key}_{j}" if len(parts) == 1 else f"{key}_{j}_{n}"
                h5.create_dataset(name, data=part)
        written = j + 1
    return written


def export_d3rlpy(
    ds: Dataset, out: str | os.PathLike, overwrite: bool = False, note: Any = None
) -> Path:
    """Write ``ds`` as the file d3rlpy's ``ReplayBuffer.dump`` writes (``d3rlpy.dataset.io.dump``,
    format 2.1), which ``ReplayBuffer.load(f, InfiniteBuffer())`` and ``import_d3rlpy`` read back.

    One d3rlpy episode per segment of at least one transition: a terminal segment of T + 1
    steps gives T rows (d3rlpy's next observation after a terminal is zeros, so the final
    observation is not kept there); any other gives all its rows, the last holding the final
    observation and the final step's action and reward (what d3rlpy's picker reads as the last
    ``next_action``; the reward counts in its returns). Dict observations of one floating dtype
    are one array, keys flattened in the task's order as ``import_d3rlpy`` splits them; others
    are a tuple of arrays in that order (``observations_<i>_<j>``). Atari frames are one (1, 84,
    84) frame per row, d3rlpy's default layout, stacked by its ``FrameStackTransitionPicker``,
    which pads an episode's start with zero frames as rlu does. A dataset imported from a dump
    is written in that dump's dtypes and row shapes. What the dump cannot hold (one-step
    segments, final steps, a terminal episode's final observation, metadata, provenance,
    attachments) goes to the sidecar ``<out>.rlu.npz`` (rlu.data.roundtrip; ``note`` gets the
    line saying so). Release windows and actions outside the action space are refused first;
    ``out`` is checked as ``export_d4rl`` checks it. Written atomically.
    """
    from rlu.data.d4rl import _require_h5py, is_sidecar
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
        raise RluError("-o is empty; give the d3rlpy dump's path")
    out = Path(out)
    if out.suffix.lower() not in (".h5", ".hdf5"):
        raise RluError(
            f"{out}: a d3rlpy dump is an HDF5 file; name the output X.h5 (as d3rlpy's "
            "datasets are named)"
        )
    check_output_file(out, [ds.path], overwrite, is_rlu_d3rlpy, "d3rlpy dump")
    side = sidecar_path(out)
    check_output_file(side, [ds.path], True, is_sidecar, "sidecar")
    h5py = _require_h5py("writing d3rlpy dumps")
    check_exportable(ds, "d3rlpy", windows=False)
    source = read_source(ds, "d3rlpy")
    info = source[0] if source else {}
    layout = info.get("layout")
    keys = ["observations", "actions", "rewards", "terminated"]
    export_id = new_export_id()
    length = np.asarray(ds.length)
    terminal = np.asarray(ds.column("is_terminal"))[np.asarray(ds.start) + length - 1]
    held = (length < 2) | terminal  # final observations the dump lacks
    make_folder(out.parent)
    try:
        with OutputLock(out, "export file"), atomic_path(out, suffix=True) as tmp:
            h5 = h5py.File(tmp, "w")
            try:
                h5.create_dataset("columns", data=keys)
                written = _write_episodes(h5, ds, keys, layout, source)
                if not written:
                    raise RluError(f"{ds.path}: every segment is a single step; nothing to export")
                h5.create_dataset("num_episodes", data=written)
                h5.create_dataset("version", data=SUPPORTED_VERSIONS[-1])
                if source is not None:  # what the import kept
                    for other in info.get("others", []):
                        h5.create_dataset(other["name"], data=source[1].read(other["key"]))
                    for name, at in (info.get("attrs") or {}).items():
                        h5.attrs[name] = (
                            at["value"] if at["kind"] == "str" else source[1].read(at["key"])
                        )
                h5.attrs["rlu_task_id"] = ds.schema.task_id or ""
                h5.attrs["rlu_export_id"] = export_id
            finally:
                with interrupts_deferred():  # a Ctrl-C here is raised after the close
                    h5.close()
            what = write_sidecar(ds, side, "d3rlpy", export_id, held)
    finally:
        if source is not None:
            source[1].__exit__()
    if note is not None:
        note(
            f"d3rlpy dumps cannot hold {', '.join(what)}: kept in {side.name} beside "
            f"{out.name}, which rlu import reads back"
        )
    return out


class _KeptRows:
    """A kept column (all episodes' rows concatenated), handed out episode by episode."""

    def __init__(self, col: Column):
        self.col, self.at = col, 0

    def take(self, n: int) -> np.ndarray:
        out = self.col.rows(self.at, self.at + n)
        self.at += n
        return out


def _kept_columns(source: Any, layout: Any) -> dict[tuple[str, int], _KeptRows]:
    out = {}
    for kind, parts in (layout or {}).items():
        for n, part in enumerate(parts):
            if part.get("kept"):
                out[(kind, n)] = _KeptRows(source[1].column(part["kept"]))
    return out


# --- the format registry's entry points (rlu.data.formats) ----------------------------------
def export(
    ds: Dataset, out: str | os.PathLike, *, overwrite: bool = False, note: Any = None
) -> Path:
    """``rlu export --format d3rlpy``: :func:`export_d3rlpy`."""
    return export_d3rlpy(ds, out, overwrite=overwrite, note=note)


def import_dataset(src: str | os.PathLike, dest: str | os.PathLike, task_id: str | None) -> Path:
    """``rlu import --format d3rlpy``: :func:`import_d3rlpy`."""
    return import_d3rlpy(src, dest, task_id)
