"""Reading a dataset: the manifest checked field by field, columns memory-mapped on first use.

A dataset folder is input like any other, and may be hostile. Before anything is mapped or
allocated:

- the manifest must be a regular JSON file of bounded size inside the folder (a FIFO, a directory
  or a symlink out of the folder is refused, never opened), every field of the kind the writer
  writes (:meth:`Schema.from_json`, whole-number counts, ``files`` exactly the schema's files
  plus any attachments under ``policies/``);
- every file resolves inside the folder, symlinks followed (a symlinked ``steps/`` or column that
  points elsewhere is refused), is a regular file, and has the size the manifest and the counts
  imply, computed in Python integers (no overflow);
- the segment index is consistent (starts are the running sum of lengths >= 1, frame starts of
  lengths + ``frame_stack`` - 1, totals equal the counts), so no view can index past a column;
- zlib offsets start at 0, never descend, end at the stream file's size, and no frame's stream is
  longer than zlib could make it; a frame inflates to exactly its declared size, never more (a
  zlib bomb costs one frame's bytes).

Every refusal is a :class:`~rlu.types.FormatError` naming the file, the field and the fix.
"""

from __future__ import annotations

import hashlib
import json
import math
import mmap
import os
import stat
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any

import numpy as np

from rlu.data.inflate import current, inflate_frames
from rlu.data.store.decoders import MEMORY, Decoders, decoders
from rlu.data.store.schema import (
    FORMAT,
    FORMAT_VERSION,
    MANIFEST,
    FieldError,
    Schema,
    is_attachment,
    partial_dir,
    whole_number,
)
from rlu.segments import METADATA_FIELDS, METADATA_MISSING, Segment
from rlu.types import ArraySpec, FormatError, RluError

if TYPE_CHECKING:
    from rlu.data.episodes import EpisodeSubset

MAX_MANIFEST_BYTES = 64 << 20
_RECREATE = "re-create the dataset (re-run the command that wrote it)"
_HEX = frozenset("0123456789abcdef")


def _fail(path: Path, what: str) -> FormatError:
    return FormatError(f"{path}: {what}; {_RECREATE}")


def _resolve_inside(root: Path, rel: str, mpath: Path) -> Path:
    """``root / rel`` if it stays inside ``root`` once symlinks are followed; else FormatError."""
    parts = PurePosixPath(rel).parts
    if not rel or PurePosixPath(rel).is_absolute() or ".." in parts or "\\" in rel:
        raise _fail(mpath, f"field 'files' names {rel!r}, which is not a path inside the dataset")
    full = root / rel
    real = os.path.realpath(full)
    base = os.path.realpath(root)
    if not real.startswith(base.rstrip(os.sep) + os.sep):
        raise FormatError(
            f"{full}: resolves to {real}, outside the dataset folder {base} (a symlink?); rlu "
            "reads only files inside a dataset's folder: copy the data in, or re-create it"
        )
    return full


def _regular_size(path: Path) -> int:
    """Size of ``path``, which must be a regular file (a FIFO would block, a directory fail)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise FormatError(f"{path}: missing; the dataset is incomplete, {_RECREATE}") from None
    except OSError as e:
        raise FormatError(f"{path}: cannot be read ({e.strerror}); {_RECREATE}") from None
    if not stat.S_ISREG(st.st_mode):
        raise FormatError(f"{path}: not a regular file (a directory, FIFO or device); {_RECREATE}")
    return st.st_size


def read_manifest(path: str | os.PathLike) -> dict[str, Any]:
    """The manifest of the dataset at ``path``, every field checked (see the module docstring)."""
    path = Path(path)
    mpath = path / MANIFEST
    if not os.path.lexists(mpath):
        partial = partial_dir(path)
        hint = f" (a partial write is at {partial})" if partial.exists() else ""
        raise FormatError(
            f"{mpath}: no manifest, so {path} is not a complete rlu dataset{hint}; "
            "re-run the command that writes it"
        )
    _resolve_inside(path, MANIFEST, mpath)
    size = _regular_size(mpath)
    if size > MAX_MANIFEST_BYTES:
        raise _fail(mpath, f"{size} bytes; a manifest is at most {MAX_MANIFEST_BYTES}")
    try:
        with open(mpath, "rb") as fh:
            manifest = json.loads(fh.read(MAX_MANIFEST_BYTES + 1).decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as e:  # JSONDecodeError is a ValueError
        raise FormatError(f"{mpath}: corrupt JSON ({e}); {_RECREATE}") from None
    except RecursionError:
        raise _fail(mpath, "JSON nested too deeply to be a manifest") from None
    except OSError as e:
        raise FormatError(f"{mpath}: cannot be read ({e.strerror}); {_RECREATE}") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise FormatError(f"{mpath}: field 'format' is not {FORMAT!r}; not an rlu dataset")
    if manifest.get("version") != FORMAT_VERSION:
        raise FormatError(
            f"{mpath}: field 'version' is {manifest.get('version')!r}; this rlu reads "
            f"version {FORMAT_VERSION}: upgrade rlu or re-convert the data"
        )
    for key in ("schema", "counts", "files", "provenance"):
        if key not in manifest:
            raise FormatError(f"{mpath}: field {key!r} is missing; {_RECREATE}")
    try:
        schema = Schema.from_json(manifest["schema"])
        _counts(manifest)
        _files(manifest, schema)
        if not isinstance(manifest["provenance"], dict):
            raise FieldError("provenance", "is not an object")
    except FieldError as e:
        raise FormatError(f"{mpath}: {e}; {_RECREATE}") from None
    return manifest


def _counts(manifest: Mapping[str, Any]) -> dict[str, int]:
    counts = manifest["counts"]
    if not isinstance(counts, Mapping):
        raise FieldError("counts", f"is a {type(counts).__name__}; an object was expected")
    out = {}
    for key in ("segments", "steps", "frames", "episodes"):
        if key not in counts:
            raise FieldError(f"counts.{key}", "is missing")
        out[key] = whole_number(counts[key], f"counts.{key}")
    return out


def _files(manifest: Mapping[str, Any], schema: Schema) -> None:
    files = manifest["files"]
    if not isinstance(files, Mapping):
        raise FieldError("files", f"is a {type(files).__name__}; an object of file entries")
    want = set(schema.files())
    have = set(files)
    unexpected = {r for r in have - want if not (isinstance(r, str) and is_attachment(r))}
    if want - have or unexpected:
        raise FieldError(
            "files",
            f"does not list the schema's files: missing {sorted(want - have)}, unexpected "
            f"{sorted(map(str, unexpected))[:5]}",
        )
    for rel, entry in files.items():
        if not isinstance(entry, Mapping):
            raise FieldError(f"files.{rel}", "is not an object with sha256 and bytes")
        sha = entry.get("sha256")
        if not (isinstance(sha, str) and len(sha) == 64 and set(sha) <= _HEX):
            raise FieldError(f"files.{rel}.sha256", f"is {sha!r}; a sha256 hex digest")
        whole_number(entry.get("bytes"), f"files.{rel}.bytes")


class Dataset:
    """A read-only view of a stored dataset; columns are memory-mapped on first use.

    Made by :func:`open_dataset`, which checks the manifest, the files and the segment index
    first.
    """

    def __init__(self, path: str | os.PathLike, manifest: Mapping[str, Any]):
        self.path = Path(path)
        self.manifest = manifest
        self.schema = Schema.from_json(manifest["schema"])
        counts = _counts(manifest)
        self.num_segments = counts["segments"]
        self.num_steps = counts["steps"]
        self.num_frames = counts["frames"]
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

    # -- files ---------------------------------------------------------------------------------
    def file(self, rel: str) -> Path:
        """The path of ``rel`` in this dataset, refused unless it resolves inside the folder."""
        return _resolve_inside(self.path, rel, self.path / MANIFEST)

    def _check_index(self) -> None:
        """Starts, lengths and frame starts agree with each other and with the counts."""
        where = self.path / "segments"
        n, steps = self.num_segments, self.num_steps
        length = np.asarray(self.length)
        if n == 0:
            if steps or self.num_frames:
                raise _fail(self.path / MANIFEST, "no segments but steps or frames are counted")
            return
        if (length < 1).any() or (length > steps).any():
            i = int(np.flatnonzero((length < 1) | (length > steps))[0])
            raise _fail(where / "length.bin", f"segment {i} has length {int(length[i])}")
        ends = np.cumsum(length)  # each length <= steps < 2**48: a wrap would show as a descent
        if (np.diff(ends) <= 0).any() or int(ends[-1]) != steps:
            raise _fail(where / "length.bin", f"lengths do not add up to counts.steps={steps}")
        bad = np.flatnonzero(np.asarray(self.start) != ends - length)
        if bad.size:
            raise _fail(
                where / "start.bin",
                f"segment {int(bad[0])} starts at step {int(self.start[bad[0]])}, not where its "
                f"predecessor ends ({int((ends - length)[bad[0]])})",
            )
        if self.schema.frame_stack > 1:
            per = length + (self.schema.frame_stack - 1)
            fends = np.cumsum(per)
            if int(fends[-1]) != self.num_frames:
                raise _fail(where / "frame_start.bin", "frames do not add up to counts.frames")
            bad = np.flatnonzero(np.asarray(self.frame_start) != fends - per)
            if bad.size:
                raise _fail(where / "frame_start.bin", f"segment {int(bad[0])}'s frame start")
        elif self.num_frames:
            raise _fail(self.path / MANIFEST, "counts.frames is not 0 without frame stacking")

    # -- columns -------------------------------------------------------------------------------
    def _segment_column(self, name: str, dtype: str) -> np.ndarray:
        return self._map(f"segments/{name}.bin", dtype, (self.num_segments,))

    def _map(self, rel: str, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
        if rel in self._cache:
            return self._cache[rel]
        path = self.file(rel)
        expected = math.prod(shape) * np.dtype(dtype).itemsize  # Python ints: no overflow
        size = _regular_size(path)
        if size != expected:
            raise FormatError(
                f"{path}: {size} bytes, the manifest implies {expected}; the file is truncated or "
                f"foreign, {_RECREATE}"
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
        """Give the resident pages of a large column back to the OS page cache (a raw column,
        or a zlib column's offsets: 8 bytes a frame, 400 MB for an Atari run of 50M frames).

        Sampling a dataset larger than RAM calls this after every batch, so the process's
        resident memory stays bounded; the data stays cached by the OS for the next batch.
        """
        for rel in (f"steps/{name}.bin", f"steps/{name}.offsets.bin"):
            mm = self._mmaps.get(rel)
            if mm is not None and mm.nbytes >= min_bytes:
                # numpy keeps a memmap's mmap.mmap in _mmap; its stubs do not declare it
                mm._mmap.madvise(mmap.MADV_DONTNEED)  # type: ignore[attr-defined]

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
            col: Any = ZlibColumn(self.file(f"steps/{name}.zlib"), offsets, spec)
        else:
            col = self._map(f"steps/{name}.bin", spec.dtype, (n, *spec.shape))
        self._cache[name] = col
        return col

    def metadata(self, key: str) -> np.ndarray:
        """One per-segment metadata field (``METADATA_FIELDS``: episode return, run, checkpoint,
        ...) as an array, one value per segment (missing values are the field's sentinel)."""
        if key not in METADATA_FIELDS:
            raise RluError(f"no metadata field {key!r}; fields: {', '.join(METADATA_FIELDS)}")
        return self._segment_column(f"meta_{key}", METADATA_FIELDS[key])

    def observation_keys(self) -> list[str]:
        """The observation column names (``observation`` or ``observation/<key>``)."""
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
        obs: np.ndarray | dict[str, np.ndarray]
        if self.schema.frame_stack > 1:
            f0, k = int(self.frame_start[i]), self.schema.frame_stack - 1
            frames = get("observation", slice(f0, f0 + k + n))
            prefix, obs = frames[:k], frames[k:]
        elif isinstance(self.schema.observation, ArraySpec):
            obs = get("observation", sl)
        else:
            obs = {k: get(f"observation/{k}", sl) for k in self.schema.observation}
        meta: dict[str, Any] = {}
        for key, dtype in METADATA_FIELDS.items():
            v = self.metadata(key)[i]
            missing = METADATA_MISSING[dtype]
            if not (v == missing or (isinstance(missing, float) and np.isnan(v))):
                meta[key] = v.item()
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
        """Every segment in order, as in-memory arrays (:meth:`segment`)."""
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
        """A summary: path, schema, counts, episode-return statistics (episodes, mean, std, min,
        p90, max) and provenance; what ``rlu info`` prints."""
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

    # -- Minari's episode API (rlu.data.episodes) ------------------------------------------------
    def set_seed(self, seed: int | None) -> None:
        """Seed the generator of :meth:`sample_episodes` (``MinariDataset.set_seed``)."""
        from rlu.data.episodes import set_seed

        set_seed(self, seed)

    def sample_episodes(self, n_episodes: int) -> list[Any]:
        """``n_episodes`` distinct episodes at random, as Minari's ``EpisodeData``."""
        from rlu.data.episodes import sample_episodes

        return sample_episodes(self, n_episodes)

    def iterate_episodes(self, episode_indices: Any = None) -> Iterator[Any]:
        """The episodes (all, or those at ``episode_indices``) as Minari's ``EpisodeData``."""
        from rlu.data.episodes import iterate_episodes

        return iterate_episodes(self, episode_indices)

    def filter_episodes(self, condition: Any) -> EpisodeSubset:
        """The dataset of the episodes for which ``condition(episode)`` holds (Minari's)."""
        from rlu.data.episodes import filter_episodes

        return filter_episodes(self, condition)

    def split(self, sizes: Any, seed: int | None = None) -> list[EpisodeSubset]:
        """Disjoint random parts: episode counts or fractions (``minari.split_dataset``)."""
        from rlu.data.episodes import split

        return split(self, sizes, seed)

    def recover_environment(self, eval_env: bool = False, **kwargs: Any) -> Any:
        """The Gymnasium env the data come from (``MinariDataset.recover_environment``)."""
        from rlu.data.episodes import recover_environment

        return recover_environment(self, eval_env, **kwargs)


def _compress_bound(n: int) -> int:
    """The most bytes zlib's deflate can make of ``n`` bytes (zlib.h ``compressBound``)."""
    return n + (n >> 12) + (n >> 14) + (n >> 25) + 13


_SHARED_FRAMES = 256  # fewer frames than this are inflated in the calling thread alone
_RUN_FRAMES = 64  # the most frames one read inflates (a long run is split between processes)
_MERGE_GAP = 16 << 10  # runs of rows whose streams lie closer than this are read at once


class ZlibColumn:
    """A compressed image column: frames decoded on demand (one zlib stream per frame).

    The offsets are checked when the column is opened, and each frame inflates to exactly its
    declared size: a damaged or hostile stream raises :class:`FormatError` naming the file and
    the row, after allocating no more than one frame.

    :meth:`take` reads the rows asked for in file order, one ``pread`` per run of adjacent rows
    (a stacked transition's frames are adjacent: one read), each row inflated once however often
    it is asked for, by the fastest installed inflater (``rlu.data.inflate``), a batch's reads
    split between the calling thread and one helper process per other core
    (``rlu.data.store.decoders``).
    """

    def __init__(self, path: Path, offsets: np.ndarray, spec: ArraySpec):
        self.path, self.offsets, self.spec = path, offsets, spec
        self.shape = (len(offsets) - 1, *spec.shape)
        self.dtype = np.dtype(spec.dtype)
        self.frame_bytes = spec.size * self.dtype.itemsize
        self._fd: int | None = None
        self.size = size = _regular_size(path)
        offsets_file = path.with_name(path.name.removesuffix(".zlib") + ".offsets.bin")
        if offsets[0] != 0 or int(offsets[-1]) != size:
            raise FormatError(
                f"{offsets_file}: offsets run from {int(offsets[0])} to {int(offsets[-1])}; the "
                f"stream file holds {size} bytes; {_RECREATE}"
            )
        bound = _compress_bound(self.frame_bytes)
        chunk = 1 << 22  # frames checked at a time: 32 MB of sizes, not 400 MB for 50M frames
        for a in range(0, len(offsets) - 1, chunk):
            sizes = np.diff(offsets[a : a + chunk + 1])
            bad = np.flatnonzero((sizes < 8) | (sizes > bound))
            if bad.size:
                raise FormatError(
                    f"{offsets_file}: frame {a + int(bad[0])} has a stream of "
                    f"{int(sizes[bad[0]])} bytes (offsets descend, or no zlib stream of a "
                    f"{self.frame_bytes}-byte frame is that size); {_RECREATE}"
                )

    def __len__(self) -> int:
        return self.shape[0]

    def _fileno(self) -> int:
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDONLY | os.O_CLOEXEC)
        return self._fd

    def take(self, rows: np.ndarray) -> np.ndarray:
        """The decoded frames of ``rows`` (any shape of row indices), as one array of ``rows.shape +
        frame shape``."""
        rows = np.asarray(rows, np.int64)
        out = np.empty((*rows.shape, *self.spec.shape), self.dtype)
        flat = rows.ravel()
        if flat.size == 0:
            return out
        if flat.min() < 0 or flat.max() >= len(self):
            raise IndexError(f"{self.path}: rows must lie in [0, {len(self)})")
        if flat.size == 1 or bool((np.diff(flat) > 0).all()):  # sorted, no repeats
            self.read_into(flat, out.reshape(flat.size, -1))
            return out
        # each distinct row inflated once, straight into its first place in the batch, in file
        # order; its other places copied from there
        order = np.argsort(flat, kind="stable")
        ordered = flat[order]
        new = np.concatenate([[True], ordered[1:] != ordered[:-1]])
        dest = out.reshape(flat.size, -1)
        self.read_into(ordered[new], dest, order[new])
        if not new.all():
            first = order[np.flatnonzero(new)[np.cumsum(new) - 1]]  # first place of each row
            dup = order[~new]
            dest[dup] = dest[first[~new]]
        return out

    def read_into(
        self, rows: np.ndarray, out: np.ndarray, places: np.ndarray | None = None
    ) -> None:
        """Inflate ``rows`` (ascending, no repeats) into rows ``places`` of ``out`` (C-contiguous,
        one frame a row; default: rows 0, 1, ...), one read per run of nearby rows, the runs
        split between this thread and the frame-inflating processes (``decoders``)."""
        starts, ends = self.offsets[rows], self.offsets[rows + 1]
        # a read: rows [a, b) from the file in one piece (nearby rows merged), at most
        # _RUN_FRAMES of them; a task: consecutive reads, about as many frames in each
        cut = np.flatnonzero(starts[1:] - ends[:-1] > _MERGE_GAP) + 1
        bounds = np.concatenate([[0], cut, [len(rows)]])
        reads: list[tuple[int, int]] = []
        for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True):
            reads.extend((i, min(i + _RUN_FRAMES, b)) for i in range(a, b, _RUN_FRAMES))
        fd = self._fileno()

        def run(task: list[tuple[int, int]]) -> None:
            for a, b in task:
                lo, hi = int(starts[a]), int(ends[b - 1])
                data = os.pread(fd, hi - lo, lo)
                if len(data) != hi - lo:
                    raise self._cut(lo, hi, len(data))
                if places is None:
                    bad = inflate_frames(data, starts[a:b] - lo, ends[a:b] - lo, out[a:b],
                                         self.frame_bytes)  # fmt: skip
                else:
                    bad = inflate_frames(data, starts[a:b] - lo, ends[a:b] - lo, out,
                                         self.frame_bytes, places[a:b])  # fmt: skip
                if bad is not None:
                    raise self._bad(int(rows[a + bad[0]]), bad[1])

        helpers = decoders() if len(rows) >= _SHARED_FRAMES and len(reads) > 1 else None
        if helpers is None or not helpers.lock.acquire(blocking=False):
            run(reads)  # one core, a small batch, or another thread's batch in the helpers
            return
        try:
            self._run_shared(helpers, rows, reads, out, places, run)
        finally:
            helpers.lock.release()

    def _run_shared(
        self,
        helpers: Decoders,
        rows: np.ndarray,
        reads: list[tuple[int, int]],
        out: np.ndarray,
        places: np.ndarray | None,
        run: Callable[[list[tuple[int, int]]], None],
    ) -> None:
        """``reads`` split by frames into a part for this thread (the first) and one per helper
        process; the first error in row order raised once every helper has answered."""
        starts, ends = self.offsets[rows], self.offsets[rows + 1]
        n = len(rows)
        parts = len(helpers.helpers) + 1
        edges = np.searchsorted([b for _, b in reads], np.linspace(0, n, parts + 1)[1:-1])
        groups = [g for g in np.split(np.arange(len(reads)), edges) if len(g)]
        mine, theirs = [reads[i] for i in groups[0]], [[reads[i] for i in g] for g in groups[1:]]
        tasks, spans = [], []
        st = os.fstat(self._fileno())
        for task in theirs:
            fa, fb = task[0][0], task[-1][1]
            if (fb - fa) * self.frame_bytes > MEMORY:  # a task too large for the shared memory
                mine.extend(task)
                continue
            local = np.asarray(task, np.int64) - fa
            file = (current(), str(self.path), st.st_dev, st.st_ino)
            tasks.append((*file, local, starts[fa:fb], ends[fa:fb], self.frame_bytes))
            spans.append((fa, fb, task))
        helpers.send(tasks)
        error: tuple[int, Exception] | None = None
        try:
            run(mine)
        except FormatError as e:
            error = (mine[0][0], e)
        for (fa, fb, task), (shared, reply) in zip(spans, helpers.collect(len(tasks)), strict=True):
            if reply is None:
                shared = shared[: (fb - fa) * self.frame_bytes].reshape(fb - fa, -1)
                dest = out.reshape(-1, self.frame_bytes)
                if places is None:
                    dest[fa:fb] = shared
                else:
                    dest[places[fa:fb]] = shared
                helpers.frames += fb - fa
                continue
            if reply[0] == "changed":  # the path holds another file now: read ours here
                try:
                    run(task)
                except FormatError as e:
                    reply = ("error", e)
                else:
                    continue
            if reply[0] == "cut":
                err = self._cut(*reply[1:])
            elif reply[0] == "bad":
                err = self._bad(int(rows[fa + reply[1]]), reply[2])
            elif reply[0] == "fail":
                err = FormatError(f"{self.path}: a frame-inflating process failed: {reply[1]}")
            else:
                err = reply[1]
            if error is None or fa < error[0]:
                error = (fa, err)
        if error is not None:
            raise error[1]

    def _cut(self, lo: int, hi: int, got: int) -> FormatError:
        return FormatError(
            f"{self.path}: {hi - lo} bytes at offset {lo} hold {got} (the file was cut since it "
            f"was opened); {_RECREATE}"
        )

    def _bad(self, row: int, why: str) -> FormatError:
        return FormatError(
            f"{self.path}: frame {row} is not a zlib stream of one {self.frame_bytes}-byte frame "
            f"({why}); {_RECREATE}"
        )

    def __getitem__(self, rows: Any) -> np.ndarray:
        if isinstance(rows, slice):
            rows = np.arange(*rows.indices(len(self)))
        return self.take(np.asarray(rows))

    def close(self) -> None:
        """Close the stream file (it is reopened on the next read)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __del__(self) -> None:
        self.close()


def open_dataset(path: str | os.PathLike, verify: bool = False) -> Dataset:
    """Open a stored dataset. The manifest, file sizes and segment index are always checked;
    ``verify=True`` also checks every sha256."""
    manifest = read_manifest(path)
    root = Path(path)
    for rel, entry in manifest["files"].items():
        p = _resolve_inside(root, rel, root / MANIFEST)
        size = _regular_size(p)
        if size != entry["bytes"]:
            raise FormatError(f"{p}: {size} bytes, the manifest says {entry['bytes']}; {_RECREATE}")
    ds = Dataset(root, manifest)
    ds._check_index()
    if verify:
        bad = verify_checksums(path, manifest)
        if bad:
            raise FormatError(f"{bad[0]}: sha256 differs from the manifest; the file is corrupt")
    return ds


def file_sha256(path: Path, chunk: int = 1 << 22) -> str:
    """The sha256 of a file's bytes (hex), read in ``chunk``-byte blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def verify_checksums(path: str | os.PathLike, manifest: Mapping[str, Any]) -> list[Path]:
    """Files whose sha256 differs from the manifest (each must lie inside the folder)."""
    root = Path(path)
    bad = []
    for rel, entry in manifest["files"].items():
        p = _resolve_inside(root, rel, root / MANIFEST)
        if not p.is_file() or file_sha256(p) != entry["sha256"]:
            bad.append(p)
    return bad
