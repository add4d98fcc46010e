"""Writing a dataset: append segments (one, many, or pre-assembled columns); finalise atomically.

Writes are atomic: everything goes to a hidden sibling directory, every file is fsynced, the
manifest is written last, and the directory is renamed into place. A crash leaves only the hidden
directory, which never loads (no manifest under the final name) and is cleared by the next writer.
One writer per destination: the writer holds :class:`rlu.locks.OutputLock` on ``dest`` from
construction to ``close()`` / ``abort()``, so a second writer fails with "in use by PID N" instead
of clearing a live writer's partial directory.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import zlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from rlu.data.store.schema import (
    ATTACHMENT_DIRS,
    FORMAT,
    FORMAT_VERSION,
    MANIFEST,
    SEGMENT_INDEX,
    Schema,
    check_cast,
    is_attachment,
    partial_dir,
    segment_columns,
)
from rlu.files import move_into_place, open_new, write_atomic
from rlu.locks import OutputLock
from rlu.segments import METADATA_FIELDS, METADATA_MISSING, Segment
from rlu.system import available_cores
from rlu.types import ArraySpec, RluError, SpecError

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
    bytes (``rlu.data.release.convert``); :class:`SegmentColumns` takes it in place of an array.
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
        """``values`` (uint8 frames) deflated one frame per zlib stream, in threads unless
        ``threaded=False``."""
        values = np.ascontiguousarray(values, dtype=dtype)
        blobs = _compress_frames(values, threaded)
        lengths = np.fromiter(map(len, blobs), np.int64, len(blobs))
        return Deflated(b"".join(blobs), lengths, values.shape, str(values.dtype))

    def __len__(self) -> int:
        return self.shape[0]


@dataclass(frozen=True)
class SegmentColumns:
    """Several segments laid end to end as the store's columns: what one append writes.

    ``columns`` holds every step column of the schema (and, with ``frame_stack > 1``, the frame
    column: each segment's ``frame_stack - 1`` prefix frames, then one frame per step); image
    columns the store deflates may be :class:`Deflated`. ``lengths`` are the segments' step
    counts; ``metadata`` maps fields of ``METADATA_FIELDS`` to one value per segment (a field left
    out is stored as missing). Build it with :meth:`of` from segments, or directly from columns
    already assembled (conversion does, in its reader processes).
    """

    columns: Mapping[str, np.ndarray | Deflated]
    lengths: np.ndarray
    metadata: Mapping[str, np.ndarray]

    @staticmethod
    def of(schema: Schema, segments: Sequence[Segment]) -> SegmentColumns:
        """``segments`` checked against ``schema`` (its messages name the column) and joined."""
        parts = [segment_columns(schema, s) for s in segments]
        if not parts:
            raise SpecError("no segments to append")
        cols = {k: np.concatenate([p[k] for p in parts]) if len(parts) > 1 else parts[0][k]
                for k in parts[0]}  # fmt: skip
        meta = {}
        for k, dtype in METADATA_FIELDS.items():
            if any(k in s.metadata for s in segments):
                meta[k] = [s.metadata.get(k, METADATA_MISSING[dtype]) for s in segments]
        lengths = np.fromiter((len(s) for s in segments), np.int64, len(segments))
        return SegmentColumns(cols, lengths, meta)  # type: ignore[arg-type]

    def __len__(self) -> int:
        return len(self.lengths)


class _RawFile:
    """An append-only file of raw little-endian bytes, hashed as it is written.

    Everything a writer produces streams through one of these (step columns, zlib streams and
    offsets, the segment index and metadata), so a writer's memory does not grow with the
    dataset: a conversion of millions of segments holds none of them.
    """

    def __init__(self, path: Path):
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self.fh = os.fdopen(open_new(path), "wb")  # new, never through a planted link
        self.hash = hashlib.sha256()

    def write(self, data: bytes) -> None:
        self.fh.write(data)
        self.hash.update(data)

    def write_array(self, values: np.ndarray, dtype: str) -> None:
        values = np.ascontiguousarray(values, dtype=dtype)
        self.write(values.astype(values.dtype.newbyteorder("<"), copy=False).tobytes())

    def close(self) -> dict[Path, dict[str, Any]]:
        if not self.fh.closed:
            _fsync_close(self.fh)
        return {self.path: {"sha256": self.hash.hexdigest(), "bytes": self.path.stat().st_size}}


class _ColumnFile:
    """An append-only raw (or per-frame zlib) column, hashed as it is written."""

    def __init__(self, root: Path, name: str, spec: ArraySpec, encoding: str):
        self.spec, self.encoding, self.count = spec, encoding, 0
        suffix = ".zlib" if encoding == "zlib" else ".bin"
        self.path = root / "steps" / f"{name}{suffix}"
        self.file = _RawFile(self.path)
        self.files = [self.file]
        if encoding == "zlib":
            self.offsets = _RawFile(root / "steps" / f"{name}.offsets.bin")
            self.offsets.write_array(np.zeros(1, np.int64), "int64")
            self.end = 0  # the stream file's size: the next frame's offset
            self.files.append(self.offsets)

    def check(self, values: np.ndarray | Deflated, rows: int) -> None:
        """Raise before anything is written if ``values`` are not ``rows`` rows of this column."""
        want = (rows, *self.spec.shape)
        if isinstance(values, Deflated):
            if self.encoding != "zlib":
                raise SpecError(f"column {self.path.name} is stored raw; it takes arrays, not zlib")
            if values.shape != want or np.dtype(values.dtype) != np.dtype(self.spec.dtype):
                raise SpecError(
                    f"column {self.path.name}: deflated rows {values.shape} {values.dtype} do "
                    f"not fit its rows of {want} {self.spec.dtype}"
                )
            if len(values.lengths) != rows or int(np.sum(values.lengths)) != len(values.data):
                raise SpecError(f"column {self.path.name}: deflated lengths disagree with data")
            return
        shape = np.shape(values)
        if shape != want:
            raise SpecError(
                f"column {self.path.name} gets shape {shape}; the schema wants {want} "
                f"(steps first, then {self.spec.shape})"
            )
        check_cast(self.path.name, np.asarray(values).dtype, self.spec.dtype)

    def append(self, values: np.ndarray | Deflated) -> None:
        if self.encoding == "zlib":
            if not isinstance(values, Deflated):
                values = Deflated.of(values, self.spec.dtype)
            self.file.write(values.data)
            ends = self.end + np.cumsum(values.lengths, dtype=np.int64)
            self.offsets.write_array(ends, "int64")
            self.end += len(values.data)
        else:  # check() refused a Deflated for a raw column
            self.file.write_array(cast(np.ndarray, values), self.spec.dtype)
        self.count += len(values)

    def close(self) -> dict[Path, dict[str, Any]]:
        return {p: e for f in self.files for p, e in f.close().items()}


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


def _metadata_column(key: str, values: Any, n: int) -> np.ndarray:
    """Per-segment values of metadata field ``key`` in its dtype, refused rather than wrapped
    (a negative episode id, a fractional run, a string)."""
    dtype = np.dtype(METADATA_FIELDS[key])
    try:
        v = np.asarray(values)
    except (ValueError, TypeError) as e:
        raise SpecError(f"segment metadata {key!r}: {e}") from None
    if v.shape != (n,):
        raise SpecError(f"segment metadata {key!r} has shape {v.shape}; want one value per segment")
    if v.dtype.kind not in "biuf":
        raise SpecError(f"segment metadata {key!r} holds {v.dtype} values; it stores {dtype}")
    if dtype.kind == "f":
        return v.astype(dtype)
    if v.dtype.kind == "f" and not np.all(np.isfinite(v) & (v == np.round(v))):
        raise SpecError(f"segment metadata {key!r} holds non-integer values; it stores {dtype}")
    info = np.iinfo(dtype)
    if v.size and not (info.min <= int(v.min()) and int(v.max()) <= info.max):
        raise SpecError(
            f"segment metadata {key!r} has values outside [{info.min}, {info.max}] ({dtype})"
        )
    return v.astype(dtype)


class DatasetWriter:
    """Appends segments to a new dataset at ``dest``; finalises atomically on ``close()``.

    Use as a context manager: an exception inside the block removes the partial directory and
    leaves nothing at ``dest``. ``dest`` must not exist unless ``overwrite=True``, and no other
    live writer may be writing it (:class:`rlu.locks.LockBusy`).
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
        self.tmp = partial_dir(self.dest)
        self._cols: dict[str, _ColumnFile] = {}
        self._index: dict[str, _RawFile] = {}  # segments/*.bin, streamed like the columns
        self._attached: dict[Path, dict[str, Any]] = {}  # policies/...: attach()
        self._frame_names = set(schema.frame_columns())
        self.num_segments = 0
        self.num_steps = 0
        self.num_frames = 0
        self.num_episodes = 0
        self._exists_check()
        self._lock = OutputLock(self.dest, "dataset").acquire()
        self._closed = False
        try:
            self._exists_check()
            if self.tmp.exists():  # left by a crashed writer (we hold the lock): safe to clear
                shutil.rmtree(self.tmp)
            self.tmp.mkdir(parents=True)
            for name, spec in {**schema.step_columns(), **schema.frame_columns()}.items():
                self._cols[name] = _ColumnFile(self.tmp, name, spec, schema.encoding(spec))
            for name in (*SEGMENT_INDEX, *(f"meta_{k}" for k in METADATA_FIELDS)):
                self._index[name] = _RawFile(self.tmp / "segments" / f"{name}.bin")
        except BaseException:
            self.abort()
            raise

    def _exists_check(self) -> None:
        if self.dest.is_symlink() or (self.dest.exists() and not self.dest.is_dir()):
            raise RluError(f"{self.dest} exists and is not a folder; choose another --out")
        if self.dest.exists() and self.overwrite and any(self.dest.iterdir()):
            if not (self.dest / MANIFEST).is_file():
                raise RluError(
                    f"{self.dest} exists and is not an rlu dataset (no {MANIFEST}); --overwrite "
                    "replaces only an rlu dataset: choose another --out or empty it yourself"
                )
        if self.dest.exists() and not self.overwrite:
            raise RluError(
                f"{self.dest} already exists; choose another --out or remove it (overwrite=True)"
            )

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def append(self, segment: Segment) -> None:
        """Check ``segment`` against the schema (nothing is written if it disagrees); append."""
        self.append_columns(SegmentColumns.of(self.schema, [segment]))

    def extend(self, segments: Iterable[Segment]) -> None:
        """Append many segments with one write per column file (same bytes as one by one)."""
        segments = list(segments)
        if segments:
            self.append_columns(SegmentColumns.of(self.schema, segments))

    def append_columns(self, batch: SegmentColumns) -> None:
        """Append segments already laid out as columns; everything is checked before a byte is
        written, so a batch that disagrees with the schema leaves the dataset as it was."""
        if self._closed:
            raise RluError(f"{self.dest}: the writer is closed; open a new DatasetWriter")
        n = len(batch)
        if n == 0:
            return
        lengths = np.asarray(batch.lengths)
        if lengths.ndim != 1 or lengths.dtype.kind not in "iu" or (lengths < 1).any():
            raise SpecError("segment lengths must be a 1D array of integers >= 1")
        lengths = lengths.astype(np.int64)
        steps = int(lengths.sum())
        k = self.schema.frame_stack
        frames = steps + n * (k - 1) if self._frame_names else 0
        names, want = set(batch.columns), set(self._cols)
        if names != want:
            raise SpecError(
                f"columns disagree with the schema: missing {sorted(want - names)}, "
                f"unexpected {sorted(names - want)}"
            )
        for name, col in self._cols.items():
            col.check(batch.columns[name], frames if name in self._frame_names else steps)
        unknown = set(batch.metadata) - set(METADATA_FIELDS)
        if unknown:
            raise SpecError(
                f"segment metadata has unknown key(s) {sorted(unknown)}; known: "
                f"{', '.join(METADATA_FIELDS)}"
            )
        meta = {k: _metadata_column(k, v, n) for k, v in batch.metadata.items()}
        ends = np.cumsum(lengths)
        first = np.asarray(batch.columns["is_first"], bool)[ends - lengths]
        last = np.asarray(batch.columns["is_last"], bool)[ends - 1]
        for name, col in self._cols.items():
            col.append(batch.columns[name])
        index = self._index
        index["start"].write_array(self.num_steps + ends - lengths, "int64")
        index["length"].write_array(lengths, "int64")
        if self._frame_names:
            per = lengths + (k - 1)
            index["frame_start"].write_array(self.num_frames + np.cumsum(per) - per, "int64")
        else:
            index["frame_start"].write_array(np.zeros(n, np.int64), "int64")
        for key, dtype in METADATA_FIELDS.items():
            values = meta[key] if key in meta else np.full(n, METADATA_MISSING[dtype], dtype)
            index[f"meta_{key}"].write_array(values, dtype)
        self.num_segments += n
        self.num_steps += steps
        self.num_frames += frames
        self.num_episodes += int((first & last).sum())

    def append_dataset(
        self, src: str | os.PathLike, on_bytes: Callable[[int], object] | None = None
    ) -> None:
        """Append every segment of the finished dataset at ``src`` (same schema), streaming its
        files: the result has the same bytes as appending its segments again, without decoding
        a frame (column bytes and zlib streams are copied, offsets and the segment index
        shifted). Assembles a dataset from parts written elsewhere (a conversion's shards on a
        cluster). Each file of ``src`` is hashed as it is read and checked against its
        manifest's sha256, so a part damaged since it was written fails here, not later.
        ``on_bytes(n)``: n more bytes of ``src`` were copied."""
        from rlu.data.store.reader import read_manifest

        if self._closed:
            raise RluError(f"{self.dest}: the writer is closed; open a new DatasetWriter")
        src = Path(src)
        manifest = read_manifest(src)
        if manifest["schema"] != json.loads(json.dumps(self.schema.to_json())):
            raise SpecError(
                f"{src}: its schema differs from {self.dest}'s; only a dataset of the same "
                "schema can be appended"
            )
        if any(is_attachment(rel) for rel in manifest["files"]):
            raise SpecError(f"{src}: holds attachments; append_dataset copies segments only")
        counts = manifest["counts"]
        copy = _Copier(src, manifest["files"], on_bytes or (lambda n: None))
        for name, col in self._cols.items():
            if col.encoding == "zlib":
                size = copy.raw(f"steps/{name}.zlib", col.file)
                copy.shifted(f"steps/{name}.offsets.bin", col.offsets, col.end, skip=1)
                col.end += size
            else:
                copy.raw(f"steps/{name}.bin", col.file)
            col.count += int(counts["frames" if name in self._frame_names else "steps"])
        index = self._index
        copy.shifted("segments/start.bin", index["start"], self.num_steps)
        copy.raw("segments/length.bin", index["length"])
        shift = self.num_frames if self._frame_names else 0
        copy.shifted("segments/frame_start.bin", index["frame_start"], shift)
        for key in METADATA_FIELDS:
            copy.raw(f"segments/meta_{key}.bin", index[f"meta_{key}"])
        self.num_segments += int(counts["segments"])
        self.num_steps += int(counts["steps"])
        self.num_frames += int(counts["frames"])
        self.num_episodes += int(counts["episodes"])

    def attach(self, rel: str, src: str | os.PathLike) -> None:
        """Copy file ``src`` into the dataset at ``rel`` (under one of ``ATTACHMENT_DIRS``, e.g.
        ``policies/run_000/checkpoint_00003.npz``); the manifest lists it with its sha256 and
        size, so ``open_dataset`` and ``rlu validate`` check it like a column."""
        if self._closed:
            raise RluError(f"{self.dest}: the writer is closed; open a new DatasetWriter")
        parts = Path(rel).parts
        if not is_attachment(rel) or ".." in parts or Path(rel).is_absolute() or "\\" in rel:
            under = " or ".join(d + "/" for d in ATTACHMENT_DIRS)
            raise RluError(
                f"attachment {rel!r}: name a file under {under} "
                "(e.g. policies/run_000/checkpoint_00000.npz)"
            )
        dest = self.tmp / rel
        if dest in self._attached:
            raise RluError(f"{self.dest}: attachment {rel} was already added")
        dest.parent.mkdir(parents=True, exist_ok=True)
        out = _RawFile(dest)
        with open(src, "rb") as fh:
            while block := fh.read(1 << 20):
                out.write(block)
        self._attached.update(out.close())

    def close(self) -> Path:
        """Write the manifest and move the dataset into place (atomically); returns its folder.
        Calling it again does nothing; a failure removes the partial folder."""
        if self._closed:
            return self.dest
        self._closed = True
        try:
            return self._finalise()
        except BaseException:
            self.abort()
            raise
        finally:
            self._lock.release()

    def _finalise(self) -> Path:
        files: dict[Path, dict[str, Any]] = {}
        closing: list[_ColumnFile | _RawFile] = [*self._cols.values(), *self._index.values()]
        for f in closing:
            files.update(f.close())
        files.update(self._attached)
        manifest = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "schema": self.schema.to_json(),
            "counts": {
                "segments": self.num_segments,
                "steps": self.num_steps,
                "frames": self.num_frames,
                "episodes": self.num_episodes,
            },
            "files": {str(p.relative_to(self.tmp)): files[p] for p in sorted(files, key=str)},
            "provenance": self.provenance,
        }
        write_atomic(self.tmp / MANIFEST, json.dumps(manifest, indent=1, sort_keys=True) + "\n")
        for d in {p.parent for p in files} | {self.tmp}:
            _fsync_dir(d)
        if self.dest.exists() and self.overwrite:
            shutil.rmtree(self.dest)
        move_into_place(self.tmp, self.dest)
        return self.dest

    def abort(self) -> None:
        """Drop everything written so far (the partial directory) and release ``dest``."""
        self._closed = True
        for f in (*(c for col in self._cols.values() for c in col.files), *self._index.values()):
            if not f.fh.closed:
                f.fh.close()
        if self._lock.held:  # only the lock holder may touch the partial directory
            shutil.rmtree(self.tmp, ignore_errors=True)
        self._lock.release()


class _Copier:
    """Streams a finished dataset's files into a writer's files, each one hashed on the way and
    checked against the source manifest (``append_dataset``)."""

    CHUNK = 8 << 20

    def __init__(self, root: Path, files: Mapping[str, Any], on_bytes: Callable[[int], object]):
        self.root, self.files, self.on_bytes = root, files, on_bytes

    def _blocks(self, rel: str, block: int) -> Iterable[bytes]:
        entry = self.files.get(rel)
        path = self.root / rel
        if entry is None:
            raise SpecError(f"{self.root}: its manifest lists no {rel}")
        h = hashlib.sha256()
        size = 0
        with open(path, "rb") as fh:
            while data := fh.read(block):
                h.update(data)
                size += len(data)
                yield data
                self.on_bytes(len(data))
        if size != entry["bytes"] or h.hexdigest() != entry["sha256"]:
            raise RluError(
                f"{path}: its bytes differ from the sha256 its manifest records (damaged since "
                "it was written); remove that dataset and write it again"
            )

    def raw(self, rel: str, out: _RawFile) -> int:
        """Copy ``rel`` as it is; returns its size."""
        n = 0
        for data in self._blocks(rel, self.CHUNK):
            out.write(data)
            n += len(data)
        return n

    def shifted(self, rel: str, out: _RawFile, shift: int, skip: int = 0) -> int:
        """Copy the int64 column ``rel`` plus ``shift``, its first ``skip`` values dropped;
        returns the values written."""
        n = 0
        for data in self._blocks(rel, self.CHUNK):  # a multiple of 8: values never split
            values = np.frombuffer(data, "<i8")
            if skip:
                values, skip = values[skip:], max(0, skip - len(values))
            out.write_array(values + shift, "int64")
            n += len(values)
        return n
