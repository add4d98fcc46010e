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
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.episode import Segment, make_episode
from rlu.data.store import DatasetWriter, Schema
from rlu.types import FormatError, RluError, install_hint

SUPPORTED_VERSIONS = ("2.1",)


def d3rlpy_segments(path: str | os.PathLike) -> Iterator[Segment]:
    """The episodes of a d3rlpy dump as whole-episode segments (see the module docstring)."""
    try:
        import h5py
    except ImportError:
        raise RluError(f"reading d3rlpy dumps needs h5py: {install_hint('interop')}") from None
    path = Path(path)
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise FormatError(
            f"{path}: not an HDF5 file ({e}); give a file from d3rlpy's dump()"
        ) from None
    with f:
        for key in ("version", "columns", "num_episodes"):
            if key not in f:
                raise FormatError(
                    f"{path}: no {key!r} entry; not a d3rlpy dump (MDPDataset.dump writes "
                    "version, columns, num_episodes)"
                )
        version = f["version"][()]
        version = version.decode() if isinstance(version, bytes) else str(version)
        if version not in SUPPORTED_VERSIONS:
            raise FormatError(
                f"{path}: field 'version' is {version!r}; rlu reads d3rlpy dump version(s) "
                f"{SUPPORTED_VERSIONS}: re-dump with d3rlpy >= 2.1"
            )
        columns = [c.decode() if isinstance(c, bytes) else str(c) for c in f["columns"][()]]
        for need in ("observations", "actions", "rewards", "terminated"):
            if need not in columns:
                raise FormatError(f"{path}: column {need!r} missing from 'columns' {columns}")
        for i in range(int(f["num_episodes"][()])):
            yield _episode(f, i, path)


def _read(f: Any, key: str, i: int, path: Path) -> Any:
    name = f"{key}_{i}"
    if name in f:
        return f[name][()]
    parts = []
    while f"{name}_{len(parts)}" in f:
        parts.append(f[f"{name}_{len(parts)}"][()])
    if not parts:
        raise FormatError(f"{path}: episode {i} has no {name!r} entry")
    return tuple(parts)


def _episode(f: Any, i: int, path: Path) -> Segment:
    obs = _read(f, "observations", i, path)
    if isinstance(obs, tuple):
        raise FormatError(f"{path}: episode {i} has tuple observations; rlu stores one array")
    actions = np.asarray(_read(f, "actions", i, path))
    rewards = np.asarray(_read(f, "rewards", i, path), np.float32).reshape(-1)
    terminated = bool(np.asarray(_read(f, "terminated", i, path)).reshape(()))
    t = len(rewards)
    if len(obs) != t or len(actions) != t:
        raise FormatError(
            f"{path}: episode {i} has {len(obs)} observations, {len(actions)} actions, {t} rewards"
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
    hold stacked frames (channels first, as d3rlpy's Atari wrappers give them, or last) and are
    stored back as single frames.
    """
    from rlu.data.d4rl import _cast, split_flat
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
                seg = _unstack_segment(seg, schema.frame_stack, f"{src}: episode {i}")
            w.append(_cast(seg, schema, i))
    return Path(dest)


def _unstack_segment(seg: Segment, k: int, where: str) -> Segment:
    from rlu.data.minari import _unstack

    obs = np.asarray(seg.observation)
    if obs.ndim >= 2 and obs.shape[1] == k and obs.shape[-1] != k:  # d3rlpy's channel-first stack
        obs = np.moveaxis(obs, 1, -1)
    if seg.is_terminal[-1]:  # the zero final observation is not a stack of the episode's frames
        frames, prefix = _unstack(obs[:-1], k, where)
        frames = np.concatenate([frames, np.zeros_like(frames[:1])])
    else:
        frames, prefix = _unstack(obs, k, where)
    return dataclasses.replace(seg, observation=frames, frame_prefix=prefix)
