"""Minari datasets out of and into the store (Minari's own code writes and reads the files).

Export (``export_minari``) turns every stored segment into one Minari episode through
``minari.create_dataset_from_buffers`` / ``update_dataset_from_buffer`` (HDF5 storage, JPEG
encoding off so that image observations stay exact):

- a segment of T steps becomes T observations and T - 1 actions, rewards, terminations and
  truncations; ``terminations[-1]`` is the segment's ``is_terminal`` end, ``truncations[-1]`` is
  set on every other end (a time limit, or the end of a release window);
- spaces: an array observation is a ``Box``; a dict observation is a *nested* ``Dict`` space, one
  level per ``/`` in rlu's flat keys
  (``walker/joints_pos`` -> ``Dict(walker=Dict(joints_pos=Box))``).
  Minari's HDF5 storage turns a ``/`` inside a key into nested HDF5 groups anyway, so a flat
  ``Dict`` keyed ``walker/joints_pos`` would not load back; the nested form round-trips exactly;
  a ``BoundedSpec`` action is a ``Box(minimum, maximum)``, a ``DiscreteSpec`` a ``Discrete(n)``;
- Atari (frames stored once, ``frame_stack`` k): Minari has no frame sharing, so each step is
  exported stacked, ``(84, 84, k)`` uint8 with the newest frame last (frames before an episode
  start are zeros, as rlu's views give them); import takes the newest frame of each step back and
  the first step's older frames as the segment's frame prefix;
- the environment: the task's Gymnasium spec (``rlu/DOMAIN-NAME-v0``, entry point
  ``rlu.envs.registration:make``, the settings the data were recorded with as kwargs: the RWRL
  challenge, the env settings of ``rlu generate``), so that Minari's own
  ``load_dataset(id).recover_environment()`` makes the env; a dataset whose schema names no
  registered task has none;
- the description says where the data came from, written from the manifest's provenance (the
  original release's files, the ``rlu generate`` command, the imported file); the whole
  provenance is in the dataset metadata as JSON (``rlu_provenance``);
- episode metadata: rlu's per-segment metadata as episode attributes ``rlu_<field>``, for
  Minari's users; dataset metadata: ``rlu_task_id``, the schema's task, and ``rlu_export_id``;
- what Minari cannot hold goes to the sidecar ``rlu_sidecar.npz`` in the dataset's folder
  (rlu.data.roundtrip): one-step segments (Minari stores no episode without a step), every
  segment's final step (the action, reward and discount no transition uses), release windows'
  first and last flags, the metadata columns, schema, provenance and attached files;
- the dataset is written into a staging folder of the datasets directory and renamed into
  place when complete; a dataset imported from Minari is written back as it was (below).

Import (``import_minari``) reads any Minari dataset (an id in ``MINARI_DATASETS_PATH`` or a
dataset directory) with Minari's own iteration, after checking every episode's arrays against its
``total_steps`` and the spaces, and its declared size, from the HDF5 metadata alone; an episode
that ends with neither a termination nor a truncation (a recording cut short) counts as
truncated. The final step of each imported episode holds no action or reward (rlu's step
semantics); rlu's own export is restored from its sidecar. Without ``--task``, the task rlu's
export recorded is the dataset's (if its schema gives the dataset's spaces). What the store does
not hold is kept in ``source/minari.json`` and ``.npz`` (every ``metadata.json`` field:
``env_spec``, ``eval_env_spec``, authors, permalink, description, reference scores; each
episode's HDF5 attributes with their dtypes, such as ``DataCollector``'s uint64 seeds, which
rlu's int64 ``seed`` column keeps only when they fit; the arrays' dtypes; float64 rewards;
``infos``; the last termination and truncation flags), from which ``export_minari`` writes the
dataset back, by default under its own id.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import shutil
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.foreign import (
    finite_array,
    fits,
    flag_array,
    h5_check,
    open_hdf5,
    real_array,
    with_final_step,
)
from rlu.data.store import Dataset, DatasetWriter, Schema
from rlu.domains import DOMAINS
from rlu.segments import METADATA_FIELDS, Segment, make_episode
from rlu.system import install_hint
from rlu.types import (
    ArraySpec,
    BoundedSpec,
    DiscreteSpec,
    FormatError,
    RluError,
    SpecError,
)

CHUNK_STEPS = 1 << 16  # episodes are handed to Minari in chunks of about this many steps


def _require_minari() -> Any:
    try:
        import minari
    except ImportError as e:
        raise RluError(
            f"Minari interop needs minari, pillow and h5py ({e}): {install_hint('interop')}"
        ) from None
    return minari


# --- spaces -----------------------------------------------------------------------------------
def _box(spec: ArraySpec) -> Any:
    import gymnasium as gym

    dtype = np.dtype(spec.dtype)
    if isinstance(spec, BoundedSpec):
        return gym.spaces.Box(spec.minimum, spec.maximum, spec.shape, dtype)
    if dtype == np.uint8:
        return gym.spaces.Box(0, 255, spec.shape, dtype)
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        return gym.spaces.Box(info.min, info.max, spec.shape, dtype)
    if dtype == np.bool_:
        return gym.spaces.Box(0, 1, spec.shape, dtype)
    return gym.spaces.Box(-np.inf, np.inf, spec.shape, dtype)


def _nest(flat: Mapping[str, Any]) -> dict[str, Any]:
    """``{'a/b': x, 'c': y}`` -> ``{'a': {'b': x}, 'c': y}``."""
    out: dict[str, Any] = {}
    for key, v in flat.items():
        parts = key.split("/")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise SpecError(f"observation key {key!r} clashes with key {p!r}")
        node[parts[-1]] = v
    return out


def _flatten(nested: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in nested.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, key + "/"))
        else:
            out[key] = v
    return out


def spaces_for(schema: Schema) -> tuple[Any, Any]:
    """(observation_space, action_space) of ``schema``'s episodes as exported to Minari."""
    import gymnasium as gym

    obs = schema.observation
    if isinstance(obs, ArraySpec):
        if schema.frame_stack > 1:
            obs = ArraySpec((*obs.shape, schema.frame_stack), obs.dtype)
        obs_space: Any = _box(obs)
    else:

        def to_space(node: Mapping[str, Any]) -> Any:
            return gym.spaces.Dict(
                {k: to_space(v) if isinstance(v, dict) else _box(v) for k, v in node.items()}
            )

        obs_space = to_space(_nest(obs))
    act = schema.action
    if isinstance(act, DiscreteSpec):
        act_space: Any = gym.spaces.Discrete(act.num_values)
    else:
        act_space = _box(act)
    return obs_space, act_space


def schema_from_spaces(observation_space: Any, action_space: Any) -> Schema:
    """A schema for a Minari dataset's spaces (Box, nested Dict of Box, Box or Discrete action)."""
    import gymnasium as gym

    def spec(space: Any, where: str) -> ArraySpec:
        if not isinstance(space, gym.spaces.Box):
            raise SpecError(f"{where} is a {type(space).__name__} space; rlu stores Box spaces")
        return ArraySpec(tuple(int(x) for x in space.shape), np.dtype(space.dtype).name)

    if isinstance(observation_space, gym.spaces.Dict):
        flat = _flatten(_space_tree(observation_space))
        obs: Any = {k: spec(s, f"observation {k!r}") for k, s in flat.items()}
    else:
        obs = spec(observation_space, "the observation")
    if isinstance(action_space, gym.spaces.Discrete):
        action: Any = DiscreteSpec((), "int64", int(action_space.n))
    elif isinstance(action_space, gym.spaces.Box):
        lo, hi = np.asarray(action_space.low), np.asarray(action_space.high)
        if not (np.all(lo == lo.flat[0]) and np.all(hi == hi.flat[0])):
            raise SpecError("the action Box has per-element bounds; rlu's BoundedSpec has one pair")
        action = BoundedSpec(
            tuple(int(x) for x in action_space.shape),
            np.dtype(action_space.dtype).name,
            float(lo.flat[0]),
            float(hi.flat[0]),
        )
    else:
        raise SpecError(f"the action space is {type(action_space).__name__}; use Box or Discrete")
    return Schema(obs, action)


def _space_tree(space: Any) -> dict[str, Any]:
    import gymnasium as gym

    return {
        k: _space_tree(s) if isinstance(s, gym.spaces.Dict) else s for k, s in space.spaces.items()
    }


# --- export -----------------------------------------------------------------------------------
def env_settings(provenance: Mapping[str, Any]) -> dict[str, Any]:
    """The env settings the data were recorded with, as ``rlu.make_env`` keyword arguments."""
    settings: dict[str, Any] = {}
    online = (provenance.get("settings") or {}).get("online") or {}
    settings.update(online.get("env_settings") or {})
    challenge = provenance.get("challenge")
    if challenge not in (None, "none"):
        settings["challenge"] = challenge
    return settings


def env_spec_for(schema: Schema, provenance: Mapping[str, Any]) -> Any:
    """The Gymnasium ``EnvSpec`` of the env the data come from, or None when the schema's task is
    not a registered task (what ``gymnasium.make`` gives for ``task.gym_id`` with those
    settings; built here without importing rlu.envs, which data/ never does)."""
    from gymnasium.envs.registration import EnvSpec

    from rlu.tasks import GYM_ENTRY_POINT, get_task

    if schema.task_id is None:
        return None
    try:
        task = get_task(schema.task_id)
    except RluError:
        return None
    if task.id != schema.task_id:
        return None
    kwargs = {"task_id": task.id, **env_settings(provenance)}
    steps = task.max_episode_steps(kwargs)
    return EnvSpec(
        id=task.gym_id, entry_point=GYM_ENTRY_POINT, kwargs=kwargs, max_episode_steps=steps
    )


def describe_provenance(provenance: Mapping[str, Any], task_id: str | None) -> str:
    """Where a dataset's data came from, in a sentence or two, from its manifest provenance."""
    p = provenance
    source = p.get("source")
    task = f"task {task_id}" if task_id else "no registered task"
    if source == "rl_unplugged release":
        files = [f["name"] for f in p.get("files", [])]
        shown = ", ".join(files[:3]) + (f" and {len(files) - 3} more" if len(files) > 3 else "")
        what = ", ".join(
            f"{k} {p[k]}" for k in ("family", "run", "challenge") if p.get(k) not in (None, "")
        )
        return (
            f"The original RL Unplugged release (Gulcehre et al. 2020, "
            f"gs://rl_unplugged) for {task} ({what}), converted by {p.get('code_version', 'rlu')}"
            + (f" from {len(files)} file(s): {shown}." if files else ".")
        )
    if "command" in p:
        settings = p.get("settings") or {}
        online = settings.get("online") or {}
        sel = p.get("selection") or {}
        parts = [f"Generated by `{p['command']}` (rlu {p.get('rlu_version', '?')}) for {task}"]
        if online.get("agent"):
            parts.append(
                f"behaviour: {online['agent']} ({online.get('preset', '?')} preset) trained "
                f"online, {settings.get('runs', '?')} run(s)"
            )
        if sel:
            parts.append(f"{sel.get('kept')} of {sel.get('recorded')} recorded episodes kept")
        if p.get("challenge"):
            parts.append(f"challenge {p['challenge']}, size {p.get('size')}")
        versions = p.get("versions") or {}
        if versions:
            parts.append("packages " + ", ".join(f"{k} {v}" for k, v in versions.items()))
        return "; ".join(parts) + "."
    if source in ("d4rl", "d3rlpy", "minari"):
        origin = p.get("file") or p.get("minari_id") or p.get("from") or "an unnamed file"
        return f"Imported by rlu from the {source} dataset {origin} for {task}."
    if source == "synthetic":
        return f"Synthetic random arrays for {task} (rlu.data.synthetic); no environment ran."
    return f"Data for {task}; provenance as recorded: {json.dumps(p, sort_keys=True)[:500]}."


def _stacked(frames: np.ndarray, k: int) -> np.ndarray:
    """(k - 1 + T, *frame) -> (T, *frame, k), newest frame last."""
    win = np.lib.stride_tricks.sliding_window_view(frames, k, axis=0)  # (T, *frame, k)
    return np.ascontiguousarray(win)


def episode_buffer(
    seg: Segment, schema: Schema, layout: Mapping[str, Any] | None = None, extra: Any = None
) -> Any:
    """One stored segment as a Minari ``EpisodeBuffer`` (see the module docstring); ``layout``
    (the dtypes of the Minari dataset the segment was imported from) and ``extra`` (its kept
    rewards, infos and end flags) give that dataset's episode back."""
    from minari.data_collector import EpisodeBuffer

    n = len(seg) - 1
    layout = layout or {}
    dtypes = layout.get("observations") or {}
    if schema.frame_stack > 1:
        k = schema.frame_stack
        prefix = seg.frame_prefix
        if prefix is None:
            frames = np.asarray(seg.observation)
            prefix = np.zeros((k - 1, *frames.shape[1:]), frames.dtype)
        obs: Any = _stacked(np.concatenate([prefix, seg.observation]), k)
    elif isinstance(seg.observation, Mapping):
        obs = {k: np.asarray(v).astype(dtypes.get(k, v.dtype), copy=False)
               for k, v in seg.observation.items()}  # fmt: skip
        obs = _nest(obs)
    else:
        obs = np.asarray(seg.observation)
        if "" in dtypes:
            obs = obs.astype(dtypes[""], copy=False)
    action = np.asarray(seg.action)[:n]
    if layout.get("actions"):
        action = action.astype(layout["actions"], copy=False)
    elif isinstance(schema.action, DiscreteSpec):
        action = action.astype(np.int64)
    terminal = bool(seg.is_terminal[-1])
    terminations = np.zeros(n, layout.get("terminations", "bool"))
    truncations = np.zeros(n, layout.get("truncations", "bool"))
    rewards = np.asarray(seg.reward, np.float32)[:n].astype(layout.get("rewards", "float32"))
    infos = None
    if n:
        terminations[-1] = terminal
        truncations[-1] = not terminal
    if extra is not None:
        if extra.get("rewards") is not None:
            rewards = extra["rewards"]
        if extra.get("actions") is not None:
            action = extra["actions"]
        kept = extra.get("observations") or {}
        if "" in kept:
            obs = kept[""]
        elif kept:
            flat = _flatten(obs)
            flat.update(kept)
            obs = _nest(flat)
        terminations[-1], truncations[-1] = extra["ends"]
        infos = extra.get("infos")
    return EpisodeBuffer(
        observations=obs,
        actions=action,
        rewards=rewards,
        terminations=terminations,
        truncations=truncations,
        infos=infos,
    )


def default_root() -> Path:
    """Minari's datasets directory: ``MINARI_DATASETS_PATH`` or ``~/.minari/datasets``."""
    env = os.environ.get("MINARI_DATASETS_PATH")
    return Path(env) if env else Path.home() / ".minari" / "datasets"


def dataset_dir(dataset_id: str, root: str | os.PathLike | None = None) -> Path:
    """The folder Minari keeps dataset ``dataset_id`` in under ``root``."""
    from minari.dataset.minari_dataset import parse_dataset_id

    try:
        namespace, name, version = parse_dataset_id(dataset_id)
    except Exception as e:  # noqa: BLE001 (minari raises several types)
        raise RluError(f"--id {dataset_id!r}: {e}; use NAMESPACE/NAME-vN") from None
    if "-v" not in dataset_id.rsplit("/", 1)[-1]:
        raise RluError(f"--id {dataset_id!r} has no version; use NAMESPACE/NAME-vN")
    base = Path(root) if root is not None else default_root()
    parts = [*(namespace.split("/") if namespace else []), f"{name}-v{version}"]
    if any(p in ("", ".", "..") for p in parts):
        raise RluError(f"--id {dataset_id!r}: a name part is empty, '.' or '..'")
    return base.joinpath(*parts)


def _write_metadata(
    path: Path, ds: Dataset, info: Mapping[str, Any] | None, export_id: str
) -> None:
    """Complete the metadata.json Minari wrote: a dataset imported from Minari gets its own
    fields back (its id aside), any other rlu's provenance, task and env spec; both the id of
    this export (which the sidecar carries too)."""
    from rlu.files import write_json

    meta = _read_own_json(path)
    if info is not None:
        meta.update({k: v for k, v in info["metadata"].items() if k != "dataset_id"})
    else:
        prov = ds.manifest.get("provenance", {})
        spec = env_spec_for(ds.schema, prov)
        meta["rlu_provenance"] = json.dumps(prov, sort_keys=True)
        if ds.schema.task_id:
            meta["rlu_task_id"] = ds.schema.task_id
        if spec is not None:
            meta["env_spec"] = spec.to_json()
    meta["rlu_export_id"] = export_id
    write_json(path, meta, indent=None)


def export_minari(
    ds: Dataset,
    dataset_id: str | None = None,
    root: str | os.PathLike | None = None,
    description: str | None = None,
    chunk_steps: int = CHUNK_STEPS,
    note: Any = None,
) -> Path:
    """Write ``ds`` as Minari dataset ``dataset_id`` (``namespace/name-vN``); returns its directory.

    ``root`` is the Minari datasets directory (default: ``MINARI_DATASETS_PATH`` or
    ``~/.minari/datasets``); it is made if missing and checked against the dataset
    (rlu.files.check_output: the new dataset's folder may not lie in, or hold, the input).
    Minari writes the dataset into a staging folder inside ``root``, which is renamed into place
    once it is complete, with its sidecar ``rlu_sidecar.npz`` (rlu.data.roundtrip: one-step
    segments, which Minari cannot store, final steps, flags, metadata; ``note`` gets the line
    saying so); on any error nothing is left. Episodes go to Minari in chunks of about
    ``chunk_steps`` steps. A dataset imported from Minari is written back as it was
    (``source/minari.*``: its dtypes, float64 rewards, infos, episode attributes and every
    metadata field: ``env_spec``, ``eval_env_spec``, authors, reference scores...), by default
    under its own id. Actions outside the action space are refused before anything is written.
    """
    import tempfile

    minari = _require_minari()
    from rlu.data.roundtrip import (
        MINARI_SIDECAR,
        check_exportable,
        new_export_id,
        read_source,
        write_sidecar,
    )
    from rlu.files import check_output, make_folder
    from rlu.locks import OutputLock

    source = read_source(ds, "minari")
    info = source[0] if source else None
    if dataset_id is None:
        if info is None:
            raise RluError("--format minari needs --id NAMESPACE/NAME-vN")
        dataset_id = str(info["metadata"]["dataset_id"])
    base = Path(root) if root is not None else default_root()
    final = dataset_dir(dataset_id, base)
    if os.path.lexists(final):
        raise RluError(f"{final}: Minari dataset {dataset_id} already exists; use another --id")
    check_output(final, [ds.path], what="Minari dataset folder", flag="--minari-dir")
    check_exportable(ds, "Minari", windows=True)
    make_folder(base)
    export_id = new_export_id()
    length = np.asarray(ds.length)
    with contextlib.ExitStack() as stack:
        stack.enter_context(OutputLock(final, "Minari dataset"))  # one writer per dataset
        if source is not None:
            stack.callback(source[1].__exit__)
        staging = Path(tempfile.mkdtemp(dir=base, prefix=".rlu-minari-"))
        stack.callback(shutil.rmtree, staging, True)
        with _datasets_root(staging), warnings.catch_warnings():
            warnings.filterwarnings("ignore", module="minari")  # author, permalink unset
            path = dataset_dir(dataset_id, staging)
            _write_minari(minari, ds, dataset_id, info, source, description, chunk_steps)
            _write_metadata(path / "data" / "metadata.json", ds, info, export_id)
            what = write_sidecar(ds, path / MINARI_SIDECAR, "minari", export_id, length < 2)
        _move_into_place(staging, path, base)
    if note is not None:
        note(
            f"Minari datasets cannot hold {', '.join(what)}: kept in {MINARI_SIDECAR} inside "
            f"{final}, which rlu import reads back"
        )
    return final


def _read_own_json(path: Path) -> dict[str, Any]:
    from rlu.files import read_bytes

    return json.loads(read_bytes(path, MAX_METADATA_BYTES, "export again"))


def _move_into_place(staging: Path, path: Path, base: Path) -> None:
    """Rename the staged dataset (or the first namespace folder ``base`` lacks) into ``base``."""
    from rlu.files import move_into_place

    rel = path.relative_to(staging)
    for i in range(1, len(rel.parts) + 1):
        part = Path(*rel.parts[:i])
        if not os.path.lexists(base / part):
            move_into_place(staging / part, base / part, base)
            return
        if (base / part).is_symlink() or not (base / part).is_dir():
            raise RluError(f"{base / part}: not a folder; Minari's namespace folders must be")
    raise RluError(f"{base / rel}: already exists; use another --id")


def _write_minari(
    minari: Any,
    ds: Dataset,
    dataset_id: str,
    info: Mapping[str, Any] | None,
    source: Any,
    description: str | None,
    chunk_steps: int,
) -> None:
    """Minari's own writer, fed ``ds``'s segments of at least one transition in chunks."""
    if info is not None:
        from minari.serialization import deserialize_space

        obs_space = deserialize_space(info["metadata"]["observation_space"])
        act_space = deserialize_space(info["metadata"]["action_space"])
    else:
        obs_space, act_space = spaces_for(ds.schema)
    prov = ds.manifest.get("provenance", {})
    desc = description or (
        describe_provenance(prov, ds.schema.task_id) + f" Exported to Minari by rlu from {ds.path}."
    )
    extras = _SourceEpisodes(info, source) if info is not None else None
    layout = info.get("layout") if info is not None else None
    mds = None
    index = 0
    for chunk in _chunks(ds, chunk_steps):
        buffers = [
            episode_buffer(s, ds.schema, layout, extras.next(i) if extras else None)
            for i, s in chunk
        ]
        if mds is None:
            mds = minari.create_dataset_from_buffers(
                dataset_id,
                buffers,
                observation_space=obs_space,
                action_space=act_space,
                algorithm_name="rlu export",
                description=desc,
                data_format="hdf5",
                jpeg_encoding=False,
            )
        else:
            mds.update_dataset_from_buffer(buffers)
        if extras is not None:
            attrs = [extras.attrs(index + j) for j in range(len(chunk))]
        else:  # for Minari's users: which episode this is (rlu's import reads the sidecar)
            attrs = [{f"rlu_{k}": v for k, v in s.metadata.items()} for _, s in chunk]
        mds.storage.update_episode_metadata(attrs, range(index, index + len(chunk)))
        index += len(chunk)
    if mds is None:
        raise RluError(f"{ds.path}: every segment is a single step; Minari cannot store it")


class _SourceEpisodes:
    """The kept parts of the Minari dataset a dataset was imported from, episode by episode."""

    def __init__(self, info: Mapping[str, Any], source: Any):
        self.info, self.z = info, source[1]
        self.cols = {k: self.z.column(k) for k in self.z.infos}
        self.at: dict[str, int] = {}
        self.ends = self.z.read("ends") if "ends" in self.z.infos else None

    def _rows(self, key: str, n: int) -> np.ndarray:
        a = self.at.get(key, 0)
        self.at[key] = a + n
        return self.cols[key].rows(a, a + n)

    def next(self, i: int) -> dict[str, Any]:
        """Episode ``i``'s kept rewards, infos and end flags (called in episode order)."""
        if self.ends is None:
            raise FormatError(f"{self.z.path}: no array 'ends'; {self.z.fix}")
        e = self.info["episodes"][i] if i < len(self.info["episodes"]) else {}
        out: dict[str, Any] = {"ends": tuple(bool(x) for x in self.ends[i])}
        steps = int(e.get("steps", 0))
        if "rewards" in self.cols:
            out["rewards"] = self._rows("rewards", steps)
        if "actions" in self.cols:
            out["actions"] = self._rows("actions", steps)
        kept = dict.fromkeys(self.info.get("layout", {}).get("observations_kept") or [])
        for k in kept:
            kept[k] = self._rows(f"observations/{k}", steps + 1)
        if kept:
            out["observations"] = kept
        if e.get("infos") is not None:
            infos = {p: self._rows(f"infos/{p}", int(n)) for p, n in e["infos"].items()}
            out["infos"] = _nest(infos)
        return out

    def attrs(self, i: int) -> dict[str, Any]:
        e = self.info["episodes"][i] if i < len(self.info["episodes"]) else {}
        return {k: _attr_value(v) for k, v in (e.get("attrs") or {}).items()}


def _chunks(ds: Dataset, chunk_steps: int) -> Iterator[list[tuple[int, Segment]]]:
    """(index among the segments Minari stores, segment) for the segments with at least one
    transition, in chunks of about ``chunk_steps`` steps (one-step segments go to the
    sidecar)."""
    chunk: list[tuple[int, Segment]] = []
    steps = index = 0
    for i in range(len(ds)):
        if int(ds.length[i]) < 2:
            continue
        seg = ds.segment(i)
        chunk.append((index, seg))
        index += 1
        steps += len(seg)
        if steps >= chunk_steps:
            yield chunk
            chunk, steps = [], 0
            from rlu.data.roundtrip import release_all

            release_all(ds)
    if chunk:
        yield chunk


def _attr_json(v: Any) -> dict[str, Any] | None:
    """An HDF5 attribute's value as JSON with its dtype (None: not a kind rlu keeps)."""
    if isinstance(v, str):
        return {"str": v}
    a = np.asarray(v)
    if a.dtype.kind not in "biuf" or a.dtype.fields is not None:
        return None
    values = a.tolist()
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        values = np.vectorize(repr)(a.astype(np.float64)).tolist() if a.ndim else repr(float(a))
    return {"dtype": a.dtype.name, "shape": list(a.shape), "value": values}


def _attr_value(j: Mapping[str, Any]) -> Any:
    if "str" in j:
        return j["str"]
    dtype = np.dtype(j["dtype"])
    v = j["value"]
    if dtype.kind == "f":
        v = np.vectorize(float)(np.asarray(v, dtype=object)) if isinstance(v, list) else float(v)
    a = np.asarray(v, dtype=dtype).reshape(j["shape"])
    return a[()] if a.ndim == 0 else a


class _datasets_root:
    """Point Minari at ``root`` for the duration of a block (it reads MINARI_DATASETS_PATH)."""

    def __init__(self, root: str | os.PathLike | None):
        self.root = None if root is None else str(Path(root).resolve())

    def __enter__(self) -> None:
        self.old = os.environ.get("MINARI_DATASETS_PATH")
        if self.root is not None:
            os.environ["MINARI_DATASETS_PATH"] = self.root

    def __exit__(self, *exc: Any) -> None:
        if self.root is None:
            return
        if self.old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = self.old


# --- import -----------------------------------------------------------------------------------
MAX_METADATA_BYTES = 16 << 20


def _check_metadata(data: Path) -> None:
    """Refuse a Minari ``metadata.json`` that Minari itself would trip on, or act on, unsafely.

    Minari builds an env from ``env_spec`` (``gym.make``: any entry point, so any code) when the
    spaces are missing, and allocates ``arange(total_episodes)`` before reading an episode; rlu
    insists on serialised spaces and on an episode count the data file can hold.
    """
    mpath = data / "metadata.json"
    fix = "re-create the dataset (minari, or rlu export --format minari)"
    if not mpath.is_file() or mpath.stat().st_size > MAX_METADATA_BYTES:
        raise FormatError(f"{mpath}: not a regular file of at most {MAX_METADATA_BYTES} bytes")
    try:
        meta = json.loads(mpath.read_bytes())
    except (ValueError, UnicodeDecodeError, RecursionError) as e:
        raise FormatError(
            f"{mpath}: not a Minari metadata JSON file ({type(e).__name__}: {e}); rlu reads only "
            "JSON metadata and never unpickles: re-create the dataset"
        ) from None
    if not isinstance(meta, dict):
        raise FormatError(f"{mpath}: holds a {type(meta).__name__}, not an object; {fix}")
    for key in ("observation_space", "action_space"):
        if not isinstance(meta.get(key), str):
            raise FormatError(
                f"{mpath}: field {key!r} is missing or not a serialised space; rlu reads spaces "
                f"from the metadata and never builds an env from env_spec: {fix}"
            )
        try:
            _check_space(json.loads(meta[key]), key)
        except (ValueError, RecursionError) as e:
            raise FormatError(f"{mpath}: field {key!r}: {e}; {fix}") from None
    if meta.get("data_format", "hdf5") not in ("hdf5", "arrow"):
        raise FormatError(f"{mpath}: field 'data_format' is {meta.get('data_format')!r}; {fix}")
    total = meta.get("total_episodes")
    stored = sum(p.stat().st_size for p in data.iterdir() if p.is_file())
    if isinstance(total, bool) or not isinstance(total, int) or not 0 <= total <= stored:
        raise FormatError(
            f"{mpath}: field 'total_episodes' is {total!r}; the data files ({stored} bytes) cannot "
            f"hold that many episodes: {fix}"
        )
    h5 = data / "main_data.hdf5"
    if meta.get("data_format", "hdf5") == "hdf5" and h5.is_file():
        import h5py

        with open_hdf5(h5, "a Minari dataset's main_data.hdf5") as f:

            def visit(name: str, obj: Any) -> None:
                if isinstance(obj, h5py.Dataset):
                    h5_check(obj, h5, name, numeric=False)

            try:
                f.visititems(visit)
            except (OSError, RuntimeError, ValueError) as e:
                raise FormatError(f"{h5}: damaged HDF5 structure ({e}); {fix}") from None
            _check_episodes(f, h5, meta, fix)


def _space_shapes(d: Mapping[str, Any], prefix: str = "") -> dict[str, tuple[int, ...]]:
    """A serialised space's leaves (checked by ``_check_space``): '' or 'a/b' -> row shape."""
    if d.get("type") == "Dict":
        out: dict[str, tuple[int, ...]] = {}
        for k, v in d["subspaces"].items():
            out.update(_space_shapes(v, f"{prefix}{k}/"))
        return out
    shape = tuple(d.get("shape") or ()) if d.get("type") == "Box" else ()
    return {prefix.rstrip("/"): shape}


def _check_episodes(f: Any, h5: Path, meta: Mapping[str, Any], fix: str) -> None:
    """Every episode's arrays as their HDF5 metadata declares them, before Minari reads a byte:
    one row per step (observations one more), rows of the spaces' shapes, infos of at most one
    row per observation, and at most ``MAX_EPISODE_BYTES`` in all; the steps add up to
    ``total_steps``. A small file declaring gigabytes is refused here, at no memory cost."""
    spaces = {k: _space_shapes(json.loads(meta[k])) for k in ("observation_space", "action_space")}
    jpeg = bool(meta.get("jpeg_encoding", True))
    total = sum(
        _check_episode(f, i, h5, spaces, jpeg, fix) for i in range(int(meta["total_episodes"]))
    )
    steps = meta.get("total_steps")
    if isinstance(steps, int) and not isinstance(steps, bool) and steps != total:
        raise FormatError(
            f"{h5.with_name('metadata.json')}: field 'total_steps' is {steps}; the episodes hold "
            f"{total}: {fix}"
        )


def _check_episode(f: Any, i: int, h5: Path, spaces: Mapping, jpeg: bool, fix: str) -> int:
    """Episode ``i``'s declared shapes and size (``_check_episodes``); returns its steps."""
    import h5py

    from rlu.data.foreign import MAX_EPISODE_BYTES

    where = f"{h5}: episode {i}"
    g = f.get(f"episode_{i}")
    if not isinstance(g, h5py.Group):
        raise FormatError(f"{where}: no group 'episode_{i}'; {fix}")

    def arr(name: str) -> Any:
        d = g.get(name)
        if not isinstance(d, h5py.Dataset) or d.shape is None or not d.shape:
            raise FormatError(f"{where}: {name!r} is missing or not an array of rows; {fix}")
        return d

    for name in ("rewards", "terminations", "truncations"):
        if arr(name).dtype.kind not in "biuf":
            raise FormatError(
                f"{where}: {name!r} holds {arr(name).dtype} values; a Minari episode's {name} are "
                f"numbers: {fix}"
            )
    steps = g.attrs.get("total_steps")  # Minari writes it; a damaged one falls back to rewards
    ok = isinstance(steps, int | np.integer) and not isinstance(steps, bool) and steps >= 0
    t = int(steps) if ok else arr("rewards").shape[0]
    size = 0
    for name in ("rewards", "terminations", "truncations"):
        d = arr(name)
        if d.shape != (t,):
            raise FormatError(f"{where}: {name!r} has shape {d.shape}; want ({t},): {fix}")
        size += d.size * d.dtype.itemsize
    leaves = (("observations", "observation_space", t + 1), ("actions", "action_space", t))
    for field, space, rows in leaves:
        for key, shape in spaces[space].items():
            name = f"{field}/{key}" if key else field
            d = arr(name)
            # JPEG-encoded frames (Minari's default for images): one blob per row, which Minari
            # decodes to the space's shape
            image = jpeg and len(shape) in (2, 3) and tuple(d.shape[1:]) != shape
            if d.shape[0] != rows or (not image and tuple(d.shape[1:]) != shape):
                raise FormatError(
                    f"{where}: {name!r} has shape {d.shape}; its space wants {rows} rows of "
                    f"{shape}: {fix}"
                )
            size += rows * math.prod(shape) if image else d.size * d.dtype.itemsize
    infos = g.get("infos")
    if isinstance(infos, h5py.Group):
        found: list[Any] = []
        infos.visititems(lambda n, o: found.append((n, o)) if isinstance(o, h5py.Dataset) else None)
        for name, obj in found:
            if obj.shape and obj.shape[0] > t + 1:
                raise FormatError(
                    f"{where}: 'infos/{name}' has {obj.shape[0]} rows; an episode of {t} steps "
                    f"holds at most {t + 1}: {fix}"
                )
            size += (obj.size or 0) * max(obj.dtype.itemsize, 1)
    if size > MAX_EPISODE_BYTES:
        raise FormatError(
            f"{where}: its arrays declare {size} bytes, more than the {MAX_EPISODE_BYTES} one "
            f"episode may hold; the file is damaged or not what it claims: {fix}"
        )
    return t


_SPACE_TYPES = ("Box", "Discrete", "Dict")


def _check_space(d: Any, field: str, depth: int = 0) -> None:
    """A serialised Minari space rlu can store, checked before Minari builds it (a Box of shape
    1e9 x 1e9 would allocate its bounds); raises ValueError naming the field."""
    if depth > 16 or not isinstance(d, dict):
        raise ValueError(f"{field} is not a (shallow) serialised space")
    kind = d.get("type")
    if kind not in _SPACE_TYPES:
        raise ValueError(f"{field} is a {kind!r} space; rlu reads {', '.join(_SPACE_TYPES)}")
    if kind == "Dict":
        subs = d.get("subspaces")
        if not isinstance(subs, dict):
            raise ValueError(f"{field}.subspaces is not an object")
        for k, v in subs.items():
            _check_space(v, f"{field}.{k}", depth + 1)
    elif kind == "Box":
        shape = d.get("shape")
        if (
            not isinstance(shape, list)
            or not all(
                isinstance(x, int) and not isinstance(x, bool) and 0 <= x <= 1 << 28 for x in shape
            )
            or len(shape) > 8
            or int(np.prod(shape, dtype=np.float64)) > 1 << 28
        ):
            raise ValueError(f"{field}.shape is {shape!r}; a list of at most 8 sizes, 2^28 values")


def load_minari(id_or_path: str | os.PathLike, root: str | os.PathLike | None = None) -> Any:
    """A ``MinariDataset`` from a dataset directory (or its ``data`` folder) or a local id."""
    minari = _require_minari()
    path = Path(id_or_path)
    if not path.is_dir():
        with _datasets_root(root):
            from minari.storage import get_dataset_path

            try:
                path = Path(get_dataset_path(str(id_or_path)))
            except Exception as e:  # noqa: BLE001 (minari raises several types for a bad id)
                raise RluError(
                    f"{id_or_path}: no such directory and no local Minari dataset of that id "
                    f"({e}); give a dataset directory or set MINARI_DATASETS_PATH"
                ) from None
        if not path.is_dir():
            raise RluError(
                f"{id_or_path}: no such directory and no local Minari dataset of that id (looked "
                f"in {path}); give a dataset directory or set MINARI_DATASETS_PATH"
            )
    data = path / "data" if (path / "data").is_dir() else path
    if not (data / "metadata.json").exists():
        raise FormatError(f"{data}: no metadata.json; not a Minari dataset directory")
    _check_metadata(data)
    try:
        return minari.MinariDataset(data)
    except Exception as e:  # noqa: BLE001 (minari raises ValueError, KeyError, AssertionError...)
        raise FormatError(
            f"{data / 'metadata.json'}: Minari cannot open the dataset ({type(e).__name__}: {e}); "
            "re-create it"
        ) from None


def minari_segments(mds: Any, schema: Schema, on_episode: Any = None) -> Iterator[Segment]:
    """The episodes of Minari dataset ``mds`` as segments in ``schema`` (see module docstring).

    Whatever Minari raises on a damaged episode (a missing ``actions`` dataset, a bad attribute)
    becomes a :class:`FormatError` naming the dataset and the episode. ``on_episode(i, ep)``
    sees each of Minari's episodes first.
    """
    where = f"Minari dataset {mds.storage.data_path}"
    try:
        indices = [int(i) for i in mds.episode_indices]
        metas = list(mds.storage.get_episode_metadata(indices))
        episodes = mds.iterate_episodes(indices)
        if len(metas) != len(indices):
            raise FormatError(f"{where}: {len(indices)} episodes but {len(metas)} metadata")
        for i, meta in zip(indices, metas, strict=True):
            try:
                ep = next(episodes)
            except StopIteration:
                raise FormatError(f"{where}: episode {i} is missing") from None
            if not isinstance(meta, Mapping):
                raise FormatError(f"{where}: episode {i}'s metadata is not a mapping")
            if on_episode is not None:
                on_episode(i, ep)
            yield _segment(ep, dict(meta), schema, where)
    except RluError:
        raise
    except Exception as e:  # noqa: BLE001 (minari and h5py raise many types on damaged data)
        raise FormatError(
            f"{where}: a damaged episode ({type(e).__name__}: {e}); re-create the dataset"
        ) from None


def _segment(ep: Any, meta: Mapping[str, Any], schema: Schema, source: str = "Minari") -> Segment:
    where = f"{source}: episode {ep.id}"
    rewards = finite_array(ep.rewards, "rewards", where).reshape(-1)
    n = len(rewards)
    if n == 0:
        raise FormatError(f"{where}: no steps (an episode needs at least one action)")
    term = flag_array(ep.terminations, "terminations", where)
    trunc = flag_array(ep.truncations, "truncations", where)
    if len(term) != n or len(trunc) != n:
        raise FormatError(
            f"{where}: {n} rewards but {len(term)} terminations, {len(trunc)} truncations"
        )
    if n > 1 and (term[:-1].any() or trunc[:-1].any()):
        raise FormatError(f"{where}: terminated or truncated before its last step")
    terminal = bool(n and term[-1])
    obs: Any = ep.observations
    prefix = None
    if isinstance(obs, Mapping):
        obs = {k: real_array(v, f"observations/{k}", where) for k, v in _flatten(obs).items()}
    else:
        obs = real_array(obs, "observations", where)
    if schema.frame_stack > 1:
        if isinstance(obs, Mapping):
            raise FormatError(f"{where}: dict observations for a frame-stacked task")
        obs, prefix = _unstack(np.asarray(obs), schema.frame_stack, where)
    actions = real_array(ep.actions, "actions", where)
    meta_out: dict[str, Any] = {}
    for k in METADATA_FIELDS:
        if f"rlu_{k}" in meta:
            meta_out[k] = np.asarray(meta[f"rlu_{k}"]).item()
    if "episode_id" not in meta_out:
        meta_out["episode_id"] = int(ep.id)
    seed = meta.get("seed")
    if "seed" not in meta_out and isinstance(seed, int | np.integer) and not isinstance(seed, bool):
        if -(1 << 63) <= int(seed) < 1 << 63:  # DataCollector's seeds are uint64: those beyond
            meta_out["seed"] = int(seed)  # int64 stay in source/minari.json (module docstring)
    try:
        seg = make_episode(obs, actions, rewards, terminal, meta_out, prefix)
    except SpecError as e:
        raise FormatError(f"{where}: {e}") from None
    is_first = bool(np.asarray(meta.get("rlu_is_first", True)))
    is_last = bool(np.asarray(meta.get("rlu_is_last", True)))
    if is_last and "rlu_final_reward" in meta:
        seg = with_final_step(
            seg,
            fits(
                np.asarray(meta.get("rlu_final_action", 0)), str(seg.action.dtype), "final", where
            ),
            float(finite_array(meta["rlu_final_reward"], "final reward", where)),
        )
        if "rlu_episode_return" in meta:  # the stored return, as exported
            seg = dataclasses.replace(
                seg, metadata={**seg.metadata, "episode_return": meta_out["episode_return"]}
            )
    if not (is_first and is_last):
        flags_first = seg.is_first.copy()
        flags_first[0] = is_first
        flags_last = seg.is_last.copy()
        flags_last[-1] = is_last
        action, reward, discount = seg.action.copy(), seg.reward.copy(), seg.discount.copy()
        if not is_last:
            action[-1] = fits(
                np.asarray(meta.get("rlu_final_action", 0)), str(action.dtype), "final", where
            )
            reward[-1] = finite_array(meta.get("rlu_final_reward", 0.0), "final reward", where)
            discount[-1] = finite_array(
                meta.get("rlu_final_discount", 1.0), "final discount", where
            )
        seg = dataclasses.replace(
            seg,
            is_first=flags_first,
            is_last=flags_last,
            action=action,
            reward=reward,
            discount=discount,
        )
    return seg


def _unstack(obs: np.ndarray, k: int, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Stacked (T, ..., k) observations -> frames (T, ...) and step 0's k - 1 older frames."""
    if obs.shape[-1] != k:
        raise FormatError(f"{where}: observations of shape {obs.shape[1:]}; want (..., {k}) frames")
    frames = obs[..., -1]
    prefix = np.moveaxis(obs[0, ..., :-1], -1, 0)
    if not np.array_equal(_stacked(np.concatenate([prefix, frames]), k), obs):
        raise FormatError(
            f"{where}: consecutive stacked observations do not share frames; rlu stores each "
            "frame once and cannot import independent stacks"
        )
    return frames, prefix


def import_minari(
    id_or_path: str | os.PathLike,
    dest: str | os.PathLike,
    task_id: str | None = None,
    root: str | os.PathLike | None = None,
) -> Path:
    """Import a Minari dataset into a new rlu dataset at ``dest``.

    With ``task_id`` the task's schema is used (observations cast to its dtypes); without, the
    task rlu's export recorded (``rlu_task_id``, or the task of an ``env_spec`` with rlu's entry
    point) when its schema gives the dataset's spaces, else a schema from the spaces alone (no
    task). The recorded id is only looked up in rlu's task registry: no env is built. What the
    store does not hold (every metadata field, episode attributes such as uint64 seeds, float64
    rewards, infos, dtypes) is kept in ``source/minari.*`` for ``export_minari``; a dataset rlu
    exported is restored from its sidecar (rlu.data.roundtrip).
    """
    from rlu.data.d4rl import append_checked
    from rlu.data.roundtrip import (
        MINARI_SIDECAR,
        attach_from_sidecar,
        find_sidecar,
        restore,
        restored_schema,
    )

    dest = Path(dest)
    mds = load_minari(id_or_path, root)
    data = Path(mds.storage.data_path)
    meta = _read_own_json(data / "metadata.json")
    where = f"Minari dataset {data.parent}"
    mark = meta.get("rlu_export_id") if isinstance(meta.get("rlu_export_id"), str) else None
    with contextlib.ExitStack() as stack:
        sc = find_sidecar(data.parent / MINARI_SIDECAR, mark, where)
        if sc is not None:
            stack.callback(sc.close)
        if task_id is not None:
            from rlu.tasks import get_task

            schema = Schema.for_task(get_task(task_id))
        else:
            try:
                schema = schema_from_spaces(mds.observation_space, mds.action_space)
            except SpecError as e:
                raise SpecError(
                    f"{id_or_path}: {e}; import it with --task for a known schema"
                ) from None
            schema = _recorded_schema(mds, schema)
        if sc is not None:
            schema = restored_schema(sc, schema if task_id else None, where)
            prov: dict[str, Any] = dict(sc.info["provenance"])
            keep = None
        else:
            prov = {"source": "minari", "minari_id": str(mds.id), "from": str(id_or_path)}
            keep = _MinariSource(mds, meta, schema, dest.parent)
            stack.callback(keep.close)
        segments: Iterator[Segment] = minari_segments(mds, schema, keep.episode if keep else None)
        if sc is not None:
            segments = restore(segments, sc, where)
        with DatasetWriter(dest, schema, prov) as w:
            for i, seg in enumerate(segments):
                append_checked(w, seg, schema, i, str(id_or_path), index_meta=sc is None)
            if sc is not None:
                attach_from_sidecar(w, sc, dest.parent)
            elif keep is not None:
                keep.finish(w)
    return dest


class _MinariSource:
    """What an import keeps of a Minari dataset that the store does not hold
    (``source/minari.json`` and ``.npz``): every field of its ``metadata.json``, each episode's
    HDF5 attributes with their dtypes (``seed``, ``options/*``, Minari's reward statistics...),
    the dtypes of its arrays, arrays the store would change (float64 rewards; observations or
    actions cast to a task's dtypes) and ``infos/*``, all episodes' rows concatenated, and each
    episode's last termination and truncation flags (an episode cut short ends with neither)."""

    def __init__(self, mds: Any, meta: Mapping[str, Any], schema: Schema, folder: Path):
        import h5py

        from rlu.data.roundtrip import SourceWriter

        self.mds, self.meta, self.schema = mds, dict(meta), schema
        self.w = SourceWriter("minari", folder)
        self.episodes: list[dict[str, Any]] = []
        self.ends: list[tuple[bool, bool]] = []
        self.layout: dict[str, Any] = {}
        self.skipped: list[str] = []
        h5 = Path(mds.storage.data_path) / "main_data.hdf5"
        self.h5 = h5py.File(h5, "r") if h5.is_file() else None

    def _stored(self, name: str, key: str = "") -> np.dtype | None:
        if name == "rewards":
            return np.dtype("float32")
        if name == "actions":
            return np.dtype(self.schema.action.dtype)
        spec = self.schema.observation
        if isinstance(spec, Mapping):
            return np.dtype(spec[key].dtype) if key in spec else None
        return np.dtype(spec.dtype)

    def _keep(self, key: str, a: np.ndarray, stored: np.dtype | None) -> bool:
        if stored is not None and not np.can_cast(a.dtype, stored, "safe"):
            self.w.spool(key, a.dtype, a.shape[1:]).append(a)
            return True
        return False

    def episode(self, i: int, ep: Any) -> None:
        e: dict[str, Any] = {"steps": len(ep.rewards)}
        rewards = np.asarray(ep.rewards)
        self.layout["rewards"] = rewards.dtype.name
        self._keep("rewards", rewards.reshape(len(rewards)), self._stored("rewards"))
        actions = np.asarray(ep.actions) if not isinstance(ep.actions, Mapping) else None
        if actions is not None:
            self.layout["actions"] = actions.dtype.name
            if self._keep("actions", actions, self._stored("actions")):
                self.layout["actions_kept"] = True
        obs = ep.observations
        flat = _flatten(obs) if isinstance(obs, Mapping) else {"": obs}
        dtypes = self.layout.setdefault("observations", {})
        for k, v in flat.items():
            v = np.asarray(v)
            dtypes[k] = v.dtype.name
            kept = self.schema.frame_stack == 1 and self._keep(
                f"observations/{k}", v, self._stored("o", k)
            )
            if kept:
                self.layout.setdefault("observations_kept", []).append(k)
        for name in ("terminations", "truncations"):
            self.layout[name] = np.asarray(getattr(ep, name)).dtype.name
        term, trunc = np.asarray(ep.terminations), np.asarray(ep.truncations)
        self.ends.append((bool(len(term) and term[-1]), bool(len(trunc) and trunc[-1])))
        infos = {}
        for path, v in _flatten(ep.infos or {}).items():
            a = np.asarray(v)
            if a.dtype.kind not in "biuf" or a.ndim == 0:
                self.skipped.append(f"episode {i} infos/{path} ({a.dtype})")
                continue
            try:
                self.w.spool(f"infos/{path}", a.dtype, a.shape[1:]).append(a)
            except RluError:
                self.skipped.append(f"episode {i} infos/{path} (its shape or dtype changes)")
                continue
            infos[path] = len(a)
        if ep.infos is not None:  # an empty infos group is kept as one
            e["infos"] = infos
        if self.h5 is not None:
            g = self.h5[f"episode_{i}"]
            attrs = {}
            for name in g.attrs:
                j = _attr_json(g.attrs[name])
                if j is None:
                    self.skipped.append(f"episode {i} attribute {name}")
                else:
                    attrs[name] = j
            e["attrs"] = attrs
        self.episodes.append(e)

    def finish(self, w: DatasetWriter) -> None:
        self.w.add("ends", np.asarray(self.ends, bool).reshape(-1, 2))
        self.w.info.update(
            metadata=self.meta, layout=self.layout, episodes=self.episodes, skipped=self.skipped
        )
        self.w.attach(w)
        if self.skipped:
            warnings.warn(
                f"{self.mds.storage.data_path}: not kept: {'; '.join(self.skipped[:5])}",
                stacklevel=3,
            )

    def close(self) -> None:
        if self.h5 is not None:
            self.h5.close()
        self.w.close()


def recorded_task(meta: Mapping[str, Any]) -> str | None:
    """The task id rlu's export wrote into Minari metadata ``meta`` (``rlu_task_id``; for older
    exports, the ``task_id`` of an ``env_spec`` whose entry point is rlu's), if it names a
    registered task; only parsed and looked up, never built."""
    from rlu.tasks import GYM_ENTRY_POINT, TASKS

    task = meta.get("rlu_task_id")
    if not isinstance(task, str) and isinstance(meta.get("env_spec"), str):
        try:
            spec = json.loads(meta["env_spec"])
        except (ValueError, RecursionError):
            spec = None
        if isinstance(spec, dict) and spec.get("entry_point") == GYM_ENTRY_POINT:
            kwargs = spec.get("kwargs")
            task = kwargs.get("task_id") if isinstance(kwargs, dict) else None
    return task if isinstance(task, str) and task in TASKS else None


def _recorded_schema(mds: Any, from_spaces: Schema) -> Schema:
    """The schema of the task rlu's export recorded, where exporting it gives the dataset's
    spaces (a dataset of another shape keeps the schema of its spaces, without a task)."""
    from rlu.tasks import TASKS, rwrl_observation_spec

    meta = json.loads((Path(mds.storage.data_path) / "metadata.json").read_bytes())
    task_id = recorded_task(meta)
    if task_id is None:
        return from_spaces
    task = TASKS[task_id]
    candidates = [Schema.for_task(task)]
    if DOMAINS[task.domain].challenges:
        candidates.append(Schema.for_task(task, observation=rwrl_observation_spec(task, "easy")))
    spaces = (mds.observation_space, mds.action_space)
    for schema in candidates:
        if spaces_for(schema) == spaces:
            return schema
    return from_spaces


# --- the format registry's entry points (rlu.data.formats) ----------------------------------
def export(
    ds: Dataset,
    out: None,
    *,
    overwrite: bool = False,
    note: Any = None,
    id: str | None = None,  # noqa: A002 - the option is --id
    minari_dir: str | os.PathLike | None = None,
) -> Path:
    """``rlu export --format minari``: :func:`export_minari` (a Minari dataset is never
    replaced: ``overwrite`` is refused)."""
    if overwrite:
        raise RluError(
            "--overwrite does not apply to Minari datasets: rlu never replaces one; give a new "
            "--id or remove the old dataset with minari.delete_dataset"
        )
    return export_minari(ds, id, root=minari_dir, note=note)


def import_dataset(
    src: str | os.PathLike,
    dest: str | os.PathLike,
    task_id: str | None,
    minari_dir: str | os.PathLike | None = None,
) -> Path:
    """``rlu import --format minari``: :func:`import_minari`."""
    return import_minari(src, dest, task_id, root=minari_dir)
