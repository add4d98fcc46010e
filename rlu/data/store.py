"""The native episode store: memory-mapped columnar files plus a JSON manifest.

Layout of a dataset directory::

    manifest.json                 schema, counts, per-file sha256 and size, provenance
    steps/<column>.bin            one raw little-endian array per step column
    steps/observation/<key>.bin   (nested keys become folders)
    steps/observation/<key>.zlib  compressed image columns: one zlib stream per frame,
    steps/observation/<key>.offsets.bin   with int64 offsets (n + 1) into the stream file
    segments/<field>.bin          per-segment index (start, length, frame_start) and metadata

Step columns: ``action``, ``reward``, ``discount``, ``is_first``, ``is_last``, ``is_terminal``
and one per observation key. With ``frame_stack > 1`` (Atari) the single observation column holds
frames, not steps: segment s owns frames
``frame_start[s] .. frame_start[s] + (frame_stack - 1) + length[s]``, the first
``frame_stack - 1`` being the frames before its step 0 (zeros at an episode start).

Writes are atomic: everything goes to a hidden sibling directory, every file is fsynced, the
manifest is written last, and the directory is renamed into place. A crash leaves only the hidden
directory, which never loads (no manifest under the final name) and is cleared by the next writer.
"""

from __future__ import annotations

import hashlib
import json
import mmap
import os
import shutil
import zlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.episode import METADATA_FIELDS, METADATA_MISSING, Segment
from rlu.types import (
    ActionSpec,
    ArraySpec,
    FormatError,
    ObservationSpec,
    RluError,
    SpecError,
    available_cores,
    observation_spec_from_json,
    observation_spec_to_json,
)

FORMAT = "rlu-episodes"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
FLAG_COLUMNS = ("is_first", "is_last", "is_terminal")
ENCODINGS = ("raw", "zlib")


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

    @staticmethod
    def for_task(task: Any, image_encoding: str = "raw", observation: Any = None) -> Schema:
        """The schema of ``task``'s datasets: Atari stores single frames stacked at sample time."""
        obs = observation if observation is not None else task.observation_spec
        frame_stack = 1
        if task.domain == "atari" and observation is None:
            frame_stack = obs.shape[-1]
            obs = ArraySpec(obs.shape[:-1], obs.dtype)
        return Schema(obs, task.action_spec, frame_stack, image_encoding, task.id)

    def observation_columns(self) -> dict[str, ArraySpec]:
        if isinstance(self.observation, ArraySpec):
            return {"observation": self.observation}
        return {f"observation/{k}": v for k, v in self.observation.items()}

    def step_columns(self) -> dict[str, ArraySpec]:
        cols = {} if self.frame_stack > 1 else dict(self.observation_columns())
        cols["action"] = ArraySpec(self.action.shape, self.action.dtype)
        cols["reward"] = ArraySpec((), "float32")
        cols["discount"] = ArraySpec((), "float32")
        for f in FLAG_COLUMNS:
            cols[f] = ArraySpec((), "bool")
        return cols

    def frame_columns(self) -> dict[str, ArraySpec]:
        return dict(self.observation_columns()) if self.frame_stack > 1 else {}

    def encoding(self, spec: ArraySpec) -> str:
        if self.image_encoding == "zlib" and spec.dtype == "uint8" and len(spec.shape) >= 2:
            return "zlib"
        return "raw"

    def to_json(self) -> dict[str, Any]:
        return {
            "observation": observation_spec_to_json(self.observation),
            "action": self.action.to_json(),
            "frame_stack": self.frame_stack,
            "image_encoding": self.image_encoding,
            "task_id": self.task_id,
        }

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> Schema:
        return Schema(
            observation_spec_from_json(d["observation"]),
            ArraySpec.from_json(d["action"]),  # type: ignore[arg-type]
            int(d["frame_stack"]),
            str(d["image_encoding"]),
            d.get("task_id"),
        )


def _col_path(root: Path, group: str, name: str, suffix: str) -> Path:
    return root / group / f"{name}{suffix}"


_ZLIB_POOL: tuple[int, Any] | None = None  # (pid, executor): never reused across a fork
_ZLIB_THREADED_FRAMES = 64


def _deflate(frames: np.ndarray) -> list[bytes]:
    return [zlib.compress(f.tobytes(), 1) for f in frames]


def _compress_frames(values: np.ndarray, threaded: bool = True) -> list[bytes]:
    """Per-frame zlib (level 1), in one contiguous chunk per core for large appends.

    zlib releases the GIL while it deflates, so chunks compress in parallel threads; the blobs
    are the same bytes in the same order as one thread would make.
    """
    global _ZLIB_POOL
    workers = min(4, available_cores())
    if not threaded or len(values) < _ZLIB_THREADED_FRAMES or workers < 2:
        return _deflate(values)
    if _ZLIB_POOL is None or _ZLIB_POOL[0] != os.getpid():
        from concurrent.futures import ThreadPoolExecutor

        _ZLIB_POOL = (os.getpid(), ThreadPoolExecutor(workers, thread_name_prefix="rlu-zlib"))
    bounds = np.linspace(0, len(values), workers + 1).astype(int)
    chunks = [values[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    parts = _ZLIB_POOL[1].map(_deflate, chunks)
    return [blob for part in parts for blob in part]


@dataclass(frozen=True)
class Deflated:
    """Rows of an image column already deflated (what a zlib column stores), made elsewhere.

    Lets a worker process compress frames so that the process owning the writer only writes
    bytes (``rlu.data.release.convert``); ``_ColumnFile.append`` takes it in place of an array.
    """

    data: bytes
    """The rows' zlib streams, concatenated."""
    lengths: np.ndarray
    """Bytes of each row's stream (int64)."""
    shape: tuple[int, ...]
    """Shape of the rows before compression, rows first."""
    dtype: str

    @staticmethod
    def of(values: np.ndarray, dtype: str, threaded: bool = True) -> Deflated:
        values = np.ascontiguousarray(values, dtype=dtype)
        blobs = _compress_frames(values, threaded)
        lengths = np.fromiter(map(len, blobs), np.int64, len(blobs))
        return Deflated(b"".join(blobs), lengths, values.shape, str(values.dtype))

    def __len__(self) -> int:
        return self.shape[0]


class _ColumnFile:
    """An append-only raw (or per-frame zlib) column, hashed as it is written."""

    def __init__(self, root: Path, group: str, name: str, spec: ArraySpec, encoding: str):
        self.spec, self.encoding, self.count = spec, encoding, 0
        self.paths: list[Path] = []
        suffix = ".zlib" if encoding == "zlib" else ".bin"
        self.path = _col_path(root, group, name, suffix)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fh = open(self.path, "wb")
        self.hash = hashlib.sha256()
        self.paths.append(self.path)
        if encoding == "zlib":
            self.offsets: list[int] = [0]
            self.offset_path = _col_path(root, group, name, ".offsets.bin")
            self.paths.append(self.offset_path)

    def append(self, values: np.ndarray | Deflated) -> None:
        if self.encoding == "zlib":
            if not isinstance(values, Deflated):
                values = Deflated.of(values, self.spec.dtype)
            want = (len(values), *self.spec.shape)
            if values.shape != want or np.dtype(values.dtype) != np.dtype(self.spec.dtype):
                raise SpecError(
                    f"column {self.path.name}: deflated rows {values.shape} {values.dtype} do "
                    f"not fit its rows of {want} {self.spec.dtype}"
                )
            self.fh.write(values.data)
            self.hash.update(values.data)
            self.offsets.extend((self.offsets[-1] + np.cumsum(values.lengths)).tolist())
        elif isinstance(values, Deflated):
            raise SpecError(f"column {self.path.name} is stored raw; it takes arrays, not zlib")
        else:
            values = np.ascontiguousarray(values, dtype=self.spec.dtype)
            data = values.astype(values.dtype.newbyteorder("<"), copy=False).tobytes()
            self.fh.write(data)
            self.hash.update(data)
        self.count += len(values)

    def close(self) -> dict[str, dict[str, Any]]:
        _fsync_close(self.fh)
        files = {self.path: {"sha256": self.hash.hexdigest(), "bytes": self.path.stat().st_size}}
        if self.encoding == "zlib":
            data = np.asarray(self.offsets, "<i8").tobytes()
            with open(self.offset_path, "wb") as fh:
                fh.write(data)
                _fsync_close(fh)
            files[self.offset_path] = {
                "sha256": hashlib.sha256(data).hexdigest(),
                "bytes": len(data),
            }
        return files


def _fsync_close(fh: Any) -> None:
    fh.flush()
    os.fsync(fh.fileno())
    fh.close()


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _partial_dir(dest: Path) -> Path:
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
        if not np.can_cast(v.dtype, spec.dtype, casting="same_kind"):
            raise SpecError(f"column {name!r} has dtype {v.dtype}; the schema wants {spec.dtype}")
    return cols


class DatasetWriter:
    """Appends segments to a new dataset at ``dest``; finalises atomically on ``close()``.

    Use as a context manager: an exception inside the block removes the partial directory and
    leaves nothing at ``dest``. ``dest`` must not exist unless ``overwrite=True``.
    """

    def __init__(
        self,
        dest: str | os.PathLike,
        schema: Schema,
        provenance: Mapping[str, Any] | None = None,
        overwrite: bool = False,
    ):
        self.dest = Path(dest)
        self.schema = schema
        self.provenance = dict(provenance or {})
        from rlu import __version__

        self.provenance.setdefault("rlu_version", __version__)
        self.overwrite = overwrite
        if self.dest.exists() and not overwrite:
            raise RluError(
                f"{self.dest} already exists; choose another --out or remove it (overwrite=True)"
            )
        self.tmp = _partial_dir(self.dest)
        if self.tmp.exists():  # left by a crashed writer: never loadable, safe to clear
            shutil.rmtree(self.tmp)
        self.tmp.mkdir(parents=True)
        self._steps = {
            name: _ColumnFile(self.tmp, "steps", name, spec, schema.encoding(spec))
            for name, spec in schema.step_columns().items()
        }
        self._frames = {
            name: _ColumnFile(self.tmp, "steps", name, spec, schema.encoding(spec))
            for name, spec in schema.frame_columns().items()
        }
        self._seg: dict[str, list[Any]] = {"start": [], "length": [], "frame_start": []}
        self._meta: dict[str, list[Any]] = {k: [] for k in METADATA_FIELDS}
        self.num_steps = 0
        self.num_frames = 0
        self.num_episodes = 0
        self._closed = False

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def append(self, segment: Segment) -> None:
        """Check ``segment`` against the schema (nothing is written if it disagrees); append."""
        cols = self._check(segment)
        for name, values in cols.items():
            (self._frames.get(name) or self._steps[name]).append(values)
        n = len(segment)
        self._seg["start"].append(self.num_steps)
        self._seg["length"].append(n)
        self._seg["frame_start"].append(self.num_frames)
        for k, dtype in METADATA_FIELDS.items():
            self._meta[k].append(segment.metadata.get(k, METADATA_MISSING[dtype]))
        self.num_steps += n
        self.num_episodes += int(bool(cols["is_first"][0]) and bool(cols["is_last"][-1]))
        if self._frames:
            self.num_frames += n + self.schema.frame_stack - 1

    def _check(self, seg: Segment) -> dict[str, np.ndarray]:
        return segment_columns(self.schema, seg)

    def close(self) -> Path:
        if self._closed:
            return self.dest
        self._closed = True
        files: dict[Path, dict[str, Any]] = {}
        for col in (*self._steps.values(), *self._frames.values()):
            files.update(col.close())
        seg_dtypes = {"start": "int64", "length": "int64", "frame_start": "int64"}
        seg_cols = {**{k: (v, seg_dtypes[k]) for k, v in self._seg.items()}}
        seg_cols.update({f"meta_{k}": (v, METADATA_FIELDS[k]) for k, v in self._meta.items()})
        for name, (values, dtype) in seg_cols.items():
            path = self.tmp / "segments" / f"{name}.bin"
            path.parent.mkdir(exist_ok=True)
            data = np.asarray(values, dtype=np.dtype(dtype).newbyteorder("<")).tobytes()
            with open(path, "wb") as fh:
                fh.write(data)
                _fsync_close(fh)
            files[path] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
        manifest = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "schema": self.schema.to_json(),
            "counts": {
                "segments": len(self._seg["start"]),
                "steps": self.num_steps,
                "frames": self.num_frames,
                "episodes": self.num_episodes,
            },
            "files": {str(p.relative_to(self.tmp)): files[p] for p in sorted(files, key=str)},
            "provenance": self.provenance,
        }
        with open(self.tmp / MANIFEST, "w") as fh:
            json.dump(manifest, fh, indent=1, sort_keys=True)
            fh.write("\n")
            _fsync_close(fh)
        for d in {p.parent for p in files} | {self.tmp}:
            _fsync_dir(d)
        if self.dest.exists() and self.overwrite:
            shutil.rmtree(self.dest)
        os.rename(self.tmp, self.dest)
        _fsync_dir(self.dest.parent)
        return self.dest

    def abort(self) -> None:
        self._closed = True
        for col in (*self._steps.values(), *self._frames.values()):
            if not col.fh.closed:
                col.fh.close()
        shutil.rmtree(self.tmp, ignore_errors=True)


class Dataset:
    """A read-only view of a stored dataset; columns are memory-mapped on first use."""

    def __init__(self, path: str | os.PathLike, manifest: Mapping[str, Any]):
        self.path = Path(path)
        self.manifest = manifest
        self.schema = Schema.from_json(manifest["schema"])
        counts = manifest["counts"]
        self.num_segments = int(counts["segments"])
        self.num_steps = int(counts["steps"])
        self.num_frames = int(counts["frames"])
        self._cache: dict[str, Any] = {}
        self._mmaps: dict[str, np.memmap] = {}
        self.start = self._segment_column("start", "int64")
        self.length = self._segment_column("length", "int64")
        self.frame_start = self._segment_column("frame_start", "int64")

    def __len__(self) -> int:
        return self.num_segments

    def __repr__(self) -> str:
        return (
            f"Dataset({str(self.path)!r}, task={self.schema.task_id}, "
            f"segments={self.num_segments}, steps={self.num_steps})"
        )

    # -- columns -------------------------------------------------------------------------------
    def _segment_column(self, name: str, dtype: str) -> np.ndarray:
        return self._map(f"segments/{name}.bin", dtype, (self.num_segments,))

    def _map(self, rel: str, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
        if rel in self._cache:
            return self._cache[rel]
        path = self.path / rel
        expected = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
        if not path.exists():
            raise FormatError(f"{path}: missing; the dataset is incomplete, re-create it")
        size = path.stat().st_size
        if size != expected:
            raise FormatError(
                f"{path}: {size} bytes, the manifest implies {expected}; the file is truncated or "
                "foreign, re-create the dataset"
            )
        if expected == 0:
            arr = np.zeros(shape, dtype)
        else:
            mm = np.memmap(path, dtype=np.dtype(dtype).newbyteorder("<"), mode="r", shape=shape)
            self._mmaps[rel] = mm
            # a plain ndarray view indexes faster than the np.memmap subclass
            arr = mm.view(np.ndarray)
        self._cache[rel] = arr
        return arr

    def release_pages(self, name: str, min_bytes: int = 256 << 20) -> None:
        """Give the resident pages of a large raw column back to the OS page cache.

        Sampling a dataset larger than RAM calls this after every batch, so the process's
        resident memory stays bounded; the data stays cached by the OS for the next batch.
        """
        mm = self._mmaps.get(f"steps/{name}.bin")
        if mm is not None and mm.nbytes >= min_bytes:
            mm._mmap.madvise(mmap.MADV_DONTNEED)

    def column(self, name: str) -> Any:
        """A step (or frame) column: a read-only memmap, or a ``ZlibColumn`` (compressed images)."""
        if name in self._cache:
            return self._cache[name]
        specs = self.schema.step_columns()
        frames = self.schema.frame_columns()
        if name in specs:
            spec, n = specs[name], self.num_steps
        elif name in frames:
            spec, n = frames[name], self.num_frames
        else:
            raise RluError(
                f"{self.path}: no column {name!r}; columns: {', '.join([*specs, *frames])}"
            )
        if self.schema.encoding(spec) == "zlib":
            offsets = self._map(f"steps/{name}.offsets.bin", "int64", (n + 1,))
            col: Any = ZlibColumn(self.path / "steps" / f"{name}.zlib", offsets, spec)
        else:
            col = self._map(f"steps/{name}.bin", spec.dtype, (n, *spec.shape))
        self._cache[name] = col
        return col

    def metadata(self, key: str) -> np.ndarray:
        if key not in METADATA_FIELDS:
            raise RluError(f"no metadata field {key!r}; fields: {', '.join(METADATA_FIELDS)}")
        return self._segment_column(f"meta_{key}", METADATA_FIELDS[key])

    def observation_keys(self) -> list[str]:
        return list(self.schema.observation_columns())

    # -- segments ------------------------------------------------------------------------------
    def segment(self, i: int) -> Segment:
        """Segment ``i`` as in-memory arrays (observations unstacked frames for Atari)."""
        if not 0 <= i < self.num_segments:
            raise IndexError(f"segment {i} out of range [0, {self.num_segments})")
        s, n = int(self.start[i]), int(self.length[i])
        sl = slice(s, s + n)

        def get(name: str, rows: slice) -> np.ndarray:
            col = self.column(name)
            if isinstance(col, ZlibColumn):
                return col.take(np.arange(rows.start, rows.stop))
            return np.array(col[rows])

        prefix = None
        if self.schema.frame_stack > 1:
            f0, k = int(self.frame_start[i]), self.schema.frame_stack - 1
            frames = get("observation", slice(f0, f0 + k + n))
            prefix, obs = frames[:k], frames[k:]
        elif isinstance(self.schema.observation, ArraySpec):
            obs = get("observation", sl)
        else:
            obs = {k: get(f"observation/{k}", sl) for k in self.schema.observation}
        meta = {}
        for k, dtype in METADATA_FIELDS.items():
            v = self.metadata(k)[i]
            missing = METADATA_MISSING[dtype]
            if not (v == missing or (isinstance(missing, float) and np.isnan(v))):
                meta[k] = v.item()
        return Segment(
            observation=obs,
            action=np.array(self.column("action")[sl]),
            reward=np.array(self.column("reward")[sl]),
            discount=np.array(self.column("discount")[sl]),
            is_first=np.array(self.column("is_first")[sl]),
            is_last=np.array(self.column("is_last")[sl]),
            is_terminal=np.array(self.column("is_terminal")[sl]),
            metadata=meta,
            frame_prefix=prefix,
        )

    def segments(self) -> Iterator[Segment]:
        for i in range(self.num_segments):
            yield self.segment(i)

    def episode_returns(self) -> np.ndarray:
        """Return of every whole episode (segments with is_first and is_last), from the rewards."""
        reward = np.asarray(self.column("reward"), np.float64)
        first = np.asarray(self.column("is_first"))[self.start]
        last = np.asarray(self.column("is_last"))[self.start + self.length - 1]
        sums = np.add.reduceat(reward, self.start) if self.num_segments else np.zeros(0)
        return sums[first & last]

    def info(self) -> dict[str, Any]:
        returns = self.episode_returns()
        stats = {}
        if returns.size:
            stats = {
                "episodes": int(returns.size),
                "mean": float(returns.mean()),
                "std": float(returns.std()),
                "min": float(returns.min()),
                "p90": float(np.percentile(returns, 90)),
                "max": float(returns.max()),
            }
        return {
            "path": str(self.path),
            "schema": self.manifest["schema"],
            "counts": self.manifest["counts"],
            "returns": stats,
            "provenance": self.manifest["provenance"],
        }


class ZlibColumn:
    """A compressed image column: frames decoded on demand (one zlib stream per frame)."""

    def __init__(self, path: Path, offsets: np.ndarray, spec: ArraySpec):
        self.path, self.offsets, self.spec = path, offsets, spec
        self.shape = (len(offsets) - 1, *spec.shape)
        self.dtype = np.dtype(spec.dtype)
        self._fd: int | None = None

    def __len__(self) -> int:
        return self.shape[0]

    def take(self, rows: np.ndarray) -> np.ndarray:
        rows = np.asarray(rows, np.int64)
        out = np.empty((*rows.shape, *self.spec.shape), self.dtype)
        flat = out.reshape(-1, self.spec.size)
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDONLY)
        starts, ends = self.offsets[rows.ravel()], self.offsets[rows.ravel() + 1]
        for j, (a, b) in enumerate(zip(starts.tolist(), ends.tolist(), strict=True)):
            flat[j] = np.frombuffer(zlib.decompress(os.pread(self._fd, b - a, a)), self.dtype)
        return out

    def __getitem__(self, rows: Any) -> np.ndarray:
        if isinstance(rows, slice):
            rows = np.arange(*rows.indices(len(self)))
        return self.take(np.asarray(rows))

    def __del__(self) -> None:
        if self._fd is not None:
            os.close(self._fd)


def read_manifest(path: str | os.PathLike) -> dict[str, Any]:
    path = Path(path)
    mpath = path / MANIFEST
    if not mpath.exists():
        partial = _partial_dir(path)
        hint = f" (a partial write is at {partial})" if partial.exists() else ""
        raise FormatError(
            f"{mpath}: no manifest, so {path} is not a complete rlu dataset{hint}; "
            "re-run the command that writes it"
        )
    try:
        manifest = json.loads(mpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise FormatError(f"{mpath}: corrupt JSON ({e}); re-create the dataset") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise FormatError(f"{mpath}: field 'format' is not {FORMAT!r}; not an rlu dataset")
    if manifest.get("version") != FORMAT_VERSION:
        raise FormatError(
            f"{mpath}: field 'version' is {manifest.get('version')!r}; this rlu reads "
            f"version {FORMAT_VERSION}: upgrade rlu or re-convert the data"
        )
    for key in ("schema", "counts", "files", "provenance"):
        if key not in manifest:
            raise FormatError(f"{mpath}: field {key!r} is missing; re-create the dataset")
    return manifest


def open_dataset(path: str | os.PathLike, verify: bool = False) -> Dataset:
    """Open a stored dataset. Sizes are always checked; ``verify=True`` also checks every sha256."""
    manifest = read_manifest(path)
    try:
        ds = Dataset(path, manifest)
    except (KeyError, TypeError, ValueError) as e:
        raise FormatError(f"{Path(path) / MANIFEST}: malformed field ({e}); re-create it") from None
    for rel, entry in manifest["files"].items():
        p = Path(path) / rel
        if not p.exists():
            raise FormatError(f"{p}: listed in the manifest but missing; re-create the dataset")
        if p.stat().st_size != entry["bytes"]:
            raise FormatError(
                f"{p}: {p.stat().st_size} bytes, the manifest says {entry['bytes']}; re-create it"
            )
    if verify:
        bad = verify_checksums(path, manifest)
        if bad:
            raise FormatError(f"{bad[0]}: sha256 differs from the manifest; the file is corrupt")
    return ds


def file_sha256(path: Path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def verify_checksums(path: str | os.PathLike, manifest: Mapping[str, Any]) -> list[Path]:
    """Files whose sha256 differs from the manifest."""
    bad = []
    for rel, entry in manifest["files"].items():
        p = Path(path) / rel
        if not p.exists() or file_sha256(p) != entry["sha256"]:
            bad.append(p)
    return bad
