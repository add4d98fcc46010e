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

import dataclasses
import math
import os
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.episode import Segment, make_episode
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
        for i in range(int(num.reshape(()))):
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
        sizes = [[sum(s.size for s in spec.values())], [s.size for s in spec.values()]]
        want = f"{list(spec)} flattened or as a tuple, in that order"
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
        obs: Any = {k: p for k, p in zip(schema.observation, parts, strict=True)}
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
    task_id: str,
    provenance: Mapping[str, Any] | None = None,
) -> Path:
    """Import a d3rlpy dump (.h5) for ``task_id`` into a new dataset at ``dest``.

    d3rlpy holds one observation array (or a tuple of them): for a task with dict observations
    one array is split into the task's keys in the task's key order (dm_control's
    ``flatten_observation`` layout), a tuple holds one array per key in that order. Atari dumps
    hold single frames (d3rlpy's default) or stacked ones (see the module docstring); both are
    stored back as single frames.
    """
    from rlu.data.d4rl import append_checked, split_flat
    from rlu.tasks import get_task

    task = get_task(task_id)
    schema = Schema.for_task(task)
    prov = {"source": "d3rlpy", "file": str(src)}
    prov.update(provenance or {})
    with DatasetWriter(dest, schema, prov) as w:
        for i, seg in enumerate(d3rlpy_segments(src, schema, episode_limit(task))):
            if isinstance(schema.observation, Mapping) and not isinstance(seg.observation, Mapping):
                seg = dataclasses.replace(
                    seg, observation=split_flat(seg.observation, schema.observation, f"{src}")
                )
            if schema.frame_stack > 1:
                frame = schema.observation.shape  # one frame; the store keeps k
                seg = _unstack_segment(seg, schema.frame_stack, f"{src}: episode {i}", frame)
            append_checked(w, seg, schema, i, str(src))
    return Path(dest)


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
def d3rlpy_episodes(ds: Dataset) -> Iterator[tuple[int, dict[str, Any]]]:
    """(segment index, the arrays of one d3rlpy episode) for every segment with a transition, as
    ``d3rlpy.dataset.Episode.serialize`` holds them (see ``export_d3rlpy``)."""
    from rlu.data.d4rl import _flat_order

    schema = ds.schema
    spec = schema.observation
    keys = None
    if isinstance(spec, Mapping):
        keys = _flat_order(schema) or list(spec)
        dtypes = {np.dtype(spec[k].dtype) for k in keys}
        flat = len(dtypes) == 1 and np.issubdtype(next(iter(dtypes)), np.floating)
    discrete = isinstance(schema.action, DiscreteSpec)
    for i in range(len(ds)):
        seg = ds.segment(i)
        if len(seg) < 2:
            continue
        terminal = bool(seg.is_terminal[-1])
        t = len(seg) - 1 if terminal else len(seg)  # d3rlpy keeps no state after a terminal
        obs: Any = seg.observation
        if keys is not None:
            shapes = {k: (-1,) if flat else spec[k].shape for k in keys}
            parts = [np.asarray(obs[k][:t]).reshape(t, *shapes[k]) for k in keys]
            obs = np.concatenate(parts, axis=1) if flat else parts
        elif schema.frame_stack > 1:  # single frames, channel first: d3rlpy's Atari layout
            obs = np.asarray(obs[:t])[:, None]
        else:
            obs = np.asarray(obs[:t])
        action = np.asarray(seg.action[:t])
        if discrete:
            action = action.astype(np.int64).reshape(t, 1)
        yield (
            i,
            {
                "observations": obs,
                "actions": action,
                "rewards": np.asarray(seg.reward[:t], np.float32).reshape(t, 1),
                "terminated": terminal,
            },
        )


def export_d3rlpy(ds: Dataset, out: str | os.PathLike) -> Path:
    """Write ``ds`` as the file d3rlpy's ``ReplayBuffer.dump`` writes (``d3rlpy.dataset.io.dump``,
    format 2.1), which ``ReplayBuffer.load(f, InfiniteBuffer())`` and ``import_d3rlpy`` read back.

    One d3rlpy episode per segment: a terminal segment of T + 1 steps gives T rows (d3rlpy's next
    observation after a terminal is zeros, so the final observation is not kept); any other gives
    all its rows, the last holding the final observation and the final step's action and reward
    (what d3rlpy's picker reads as the last ``next_action``; the reward counts in its returns).
    Dict observations of one floating dtype are one array, keys flattened in the task's order as
    ``import_d3rlpy`` splits them; others are a tuple of arrays in that order
    (``observations_<i>_<j>``). Atari frames are one (1, 84, 84) frame per row, d3rlpy's
    default layout, stacked by its ``FrameStackTransitionPicker``, which pads an episode's start
    with zero frames as rlu does. A segment without a transition (one step) is left out, as
    d3rlpy's buffers leave out an episode without a transition, with a warning; so is the frame
    prefix of a segment that starts inside an episode (a release window), noted in a warning.
    Written atomically (a temp name, then rename).
    """
    from rlu.data.d4rl import _require_h5py

    out = Path(out)
    if out.suffix.lower() not in (".h5", ".hdf5"):
        raise RluError(
            f"{out}: a d3rlpy dump is an HDF5 file; name the output X.h5 (as d3rlpy's "
            "datasets are named)"
        )
    h5py = _require_h5py("writing d3rlpy dumps")
    if not out.parent.is_dir():
        raise RluError(f"{out}: the folder {out.parent} does not exist; create it first")
    from rlu.files import interrupts_deferred
    from rlu.locks import OutputLock

    keys = ["observations", "actions", "rewards", "terminated"]
    tmp = out.with_name(f".{out.name}.partial{out.suffix}")
    written = 0
    lock = OutputLock(out, "export file").acquire()  # one writer per output file
    try:
        h5 = h5py.File(tmp, "w")
        try:
            h5.create_dataset("columns", data=keys)
            episodes = d3rlpy_episodes(ds)
            for j, (_, ep) in enumerate(episodes):
                for key in keys:
                    value = ep[key]
                    if isinstance(value, list):
                        for n, part in enumerate(value):
                            h5.create_dataset(f"{key}_{j}_{n}", data=part)
                    else:
                        h5.create_dataset(f"{key}_{j}", data=value)
                written = j + 1
            if not written:
                raise RluError(f"{ds.path}: every segment is a single step; nothing to export")
            h5.create_dataset("num_episodes", data=written)
            h5.create_dataset("version", data=SUPPORTED_VERSIONS[-1])
        finally:
            with interrupts_deferred():  # a Ctrl-C here is raised after the close
                h5.close()
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
        lock.release()
    _warn_lossy(ds, written)
    return out


def _warn_lossy(ds: Dataset, written: int) -> None:
    single = int((np.asarray(ds.length) < 2).sum())
    if single:
        warnings.warn(
            f"{single} single-step segment(s) of {ds.path} hold no transition and were left out "
            "of the d3rlpy dump (d3rlpy keeps no episode without a transition)",
            stacklevel=3,
        )
    if ds.schema.frame_stack > 1:
        first = np.asarray(ds.column("is_first"))[np.asarray(ds.start)]
        inside = int((~first & (np.asarray(ds.length) >= 2)).sum())
        if inside:
            warnings.warn(
                f"{inside} segment(s) of {ds.path} start inside an episode (release windows): "
                "d3rlpy pads their first stacks with zero frames, not the frames before them",
                stacklevel=3,
            )
