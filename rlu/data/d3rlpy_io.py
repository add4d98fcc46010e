"""Import of d3rlpy's dataset dump (``MDPDataset.dump`` / ``ReplayBuffer.dump``, format 2.1).

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
  observation, its action is kept in the final step (d3rlpy's ``next_action`` of the last
  transition) and its reward is not (d3rlpy never uses it in a transition).

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
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.episode import Segment, make_episode
from rlu.data.foreign import (
    finite_array,
    flag_array,
    h5_array,
    h5_check,
    open_hdf5,
    real_array,
)
from rlu.data.store import DatasetWriter, Schema
from rlu.types import FormatError, RluError

SUPPORTED_VERSIONS = ("2.1",)


def d3rlpy_segments(path: str | os.PathLike) -> Iterator[Segment]:
    """The episodes of a d3rlpy dump as whole-episode segments (see the module docstring)."""
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
        num = np.asarray(h5_array(f["num_episodes"], path, "num_episodes"))
        if num.size != 1 or num.dtype.kind not in "iu" or not 0 <= int(num.reshape(())) < 1 << 40:
            raise FormatError(f"{path}: 'num_episodes' is {num!r}; a count of episodes")
        for i in range(int(num.reshape(()))):
            yield _episode(f, i, path)


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


def _read(f: Any, key: str, i: int, path: Path) -> Any:
    name = f"{key}_{i}"
    if name in f:
        return h5_array(f[name], path, name)
    parts = []
    while f"{name}_{len(parts)}" in f:
        parts.append(h5_array(f[f"{name}_{len(parts)}"], path, f"{name}_{len(parts)}"))
    if not parts:
        raise FormatError(f"{path}: episode {i} has no {name!r} entry")
    return tuple(parts)


def _episode(f: Any, i: int, path: Path) -> Segment:
    obs = _read(f, "observations", i, path)
    if isinstance(obs, tuple):
        raise FormatError(f"{path}: episode {i} has tuple observations; rlu stores one array")
    where = f"{path}: episode {i}"
    actions = real_array(_read(f, "actions", i, path), "actions", where)
    rewards = finite_array(_read(f, "rewards", i, path), "rewards", where).reshape(-1)
    terminated = flag_array(_read(f, "terminated", i, path), "terminated", where)
    if terminated.size != 1:
        raise FormatError(f"{where}: 'terminated' holds {terminated.size} values; want one")
    terminated = bool(terminated[0])
    t = len(rewards)
    if obs.ndim == 0 or actions.ndim == 0 or len(obs) != t or len(actions) != t:
        raise FormatError(
            f"{where}: {np.shape(obs)[:1]} observations, {np.shape(actions)[:1]} actions, {t} "
            "rewards; want one of each per step"
        )
    if t == 0:
        raise FormatError(f"{path}: episode {i} is empty")
    if terminated:
        final = np.zeros_like(obs[:1])
        return make_episode(np.concatenate([obs, final]), actions, rewards, True)
    seg = make_episode(obs, actions[:-1], rewards[:-1], False)
    action = seg.action.copy()
    action[-1] = actions[-1]
    return dataclasses.replace(seg, action=action)


def import_d3rlpy(
    src: str | os.PathLike,
    dest: str | os.PathLike,
    task_id: str,
    provenance: Mapping[str, Any] | None = None,
) -> Path:
    """Import a d3rlpy dump (.h5) for ``task_id`` into a new dataset at ``dest``.

    d3rlpy holds one observation array: for a task with dict observations it is split into the
    task's keys in the task's key order (dm_control's ``flatten_observation`` layout). Atari dumps
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
        for i, seg in enumerate(d3rlpy_segments(src)):
            if isinstance(schema.observation, Mapping):
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
