"""Exact round trips through D4RL, d3rlpy and Minari: what those formats cannot hold, kept aside.

**rlu's dataset -> export -> import.** The formats hold whole episodes of at least one transition,
as their readers know them. rlu's datasets hold more: each segment's final step (the action,
reward and discount no transition uses, kept as recorded: a control-suite episode's last action,
an Atari episode's last reward), segments of one step, release windows' first and last flags,
per-segment metadata (episode ids, returns, runs, seeds, checkpoints), the schema, the
provenance and attached files (behaviour policies, ``source/``). An export writes these into a
*sidecar* beside the file, ``<file>.rlu.npz`` (in a Minari dataset's folder,
``rlu_sidecar.npz``), and marks the file with the sidecar's export id (D4RL
``metadata/rlu/export_id``, d3rlpy the root attribute ``rlu_export_id``, Minari ``rlu_export_id``
in ``metadata.json``). ``rlu import`` of the file reads the sidecar back when the ids match and
the file's episodes agree with it; without the sidecar the file imports as its format's readers
see it (and says what it could not restore).

Sidecar layout, an .npz archive of plain arrays (S segments, M of them with a final observation
the file lacks: one-step segments, and terminal episodes in d3rlpy's dumps)::

    rlu/sidecar                 uint8: JSON {format, version, export_id, target, schema,
                                provenance, attachments}
    segments/length             int64 (S,)
    segments/is_first           bool (S,): the first step's flag (False for a window)
    segments/is_last            bool (S,): the final step's flag
    segments/final_action       (S, *action): the final step's action
    segments/final_reward       float32 (S,)
    segments/final_discount     float32 (S,)
    segments/final_terminal     bool (S,)
    segments/meta_<field>       (S,): each metadata column as stored (missing values included)
    segments/held_observation   int64 (M,): the segments below
    segments/final_observation  (M, ...), or segments/final_observation/<key>: their final
                                observations (for Atari, frames)
    segments/frame_prefix       (M, k - 1, ...): Atari, their frame prefixes
    attachments/<path>          uint8: each attached file's bytes

**A foreign file -> import -> export** keeps what the store's columns do not hold (float64
rewards, a file's other arrays, attributes, dtypes, its layout) as attachments
``source/<format>.json`` and ``source/<format>.npz`` of the dataset; each format's module says
what it keeps there (rlu.data.d4rl, rlu.data.d3rlpy_io, rlu.data.minari).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import secrets
import tempfile
import zipfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, cast

import numpy as np

from rlu.data.foreign import READ_BYTES, Column, NpzFile, iter_blocks
from rlu.data.store import Dataset, DatasetWriter, Schema
from rlu.data.store.reader import ZlibColumn
from rlu.data.store.schema import action_problem, is_attachment
from rlu.segments import METADATA_FIELDS, METADATA_MISSING, Segment
from rlu.types import ArraySpec, FormatError, RluError

SIDECAR_FORMAT = "rlu-export-sidecar"
SIDECAR_VERSION = 1
SIDECAR_SUFFIX = ".rlu.npz"
MINARI_SIDECAR = "rlu_sidecar.npz"
MAX_SIDECAR_JSON = 64 << 20
MAX_TABLE_BYTES = 256 << 20
"""The most a sidecar's per-segment table may declare (about 3 M segments of a 38-float action:
the most release windows a dataset of one task holds is far less)."""
MAX_ATTACHMENT_BYTES = 4 << 30
MAX_SOURCE_JSON = 64 << 20


def new_export_id() -> str:
    return secrets.token_hex(8)


def sidecar_path(out: str | os.PathLike) -> Path:
    """The sidecar of an exported file ``out`` (``X.hdf5`` -> ``X.hdf5.rlu.npz``)."""
    out = Path(out)
    return out.with_name(out.name + SIDECAR_SUFFIX)


# --- .npz written a block at a time ---------------------------------------------------------
class NpzWriter:
    """An .npz archive (what ``numpy.load`` reads) written member by member, each member a
    block of rows at a time: memory holds one block, whatever the arrays' sizes. ZIP64, so
    members may exceed 4 GiB."""

    def __init__(self, path: str | os.PathLike, compress: bool = False):
        self.zf = zipfile.ZipFile(path, "w", allowZip64=True)
        self.compress = compress

    def __enter__(self) -> NpzWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.zf.close()

    def add(self, key: str, a: Any, compress: bool | None = None) -> None:
        a = np.asarray(a)
        if a.dtype.hasobject:
            raise RluError(f"{key}: an object array; rlu writes plain arrays only (no pickle)")
        with self.member(key, a.shape, a.dtype, compress) as write:
            if a.ndim and a.shape[0]:
                for i, j in iter_blocks(a.shape[0], max(1, a[0].nbytes)):
                    write(a[i:j])
            else:
                write(a)

    @contextlib.contextmanager
    def member(
        self, key: str, shape: tuple[int, ...], dtype: Any, compress: bool | None = None
    ) -> Iterator[Callable[[np.ndarray], None]]:
        """``with w.member(key, shape, dtype) as write: write(rows)...``: the rows, in order,
        must fill ``shape`` exactly."""
        dtype = np.dtype(dtype)
        fmt = np.lib.format
        info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
        deflate = self.compress if compress is None else compress
        info.compress_type = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
        header = {"descr": fmt.dtype_to_descr(dtype), "fortran_order": False, "shape": shape}
        want = math.prod(shape) * dtype.itemsize
        done = 0
        with self.zf.open(info, "w", force_zip64=True) as fp:
            try:
                fmt.write_array_header_1_0(fp, header)
            except ValueError:  # a header over 64 KiB (a very long shape): version 2
                fmt.write_array_header_2_0(fp, header)

            def write(rows: np.ndarray) -> None:
                nonlocal done
                data = np.ascontiguousarray(rows, dtype).tobytes()
                done += len(data)
                if done > want:
                    raise RluError(f"{key}: more rows than its shape {shape} (a bug in rlu)")
                fp.write(data)

            yield write
        if done != want:
            raise RluError(f"{key}: {done} of {want} bytes written (a bug in rlu)")


@contextlib.contextmanager
def spool(folder: Path) -> Iterator[Any]:
    """An anonymous temporary file in ``folder`` (no name anyone can plant a link at)."""
    with tempfile.TemporaryFile(dir=folder) as fh:
        yield fh


def release_all(ds: Dataset) -> None:
    """Give every column's resident pages back (``Dataset.release_pages``): an export reads the
    columns front to back once, and without this the pages it read would stay in its resident
    memory, the whole dataset's size by the end."""
    for name in (*ds.schema.step_columns(), *ds.schema.frame_columns()):
        ds.release_pages(name, min_bytes=0)


# --- what an export can hold ----------------------------------------------------------------
def check_exportable(ds: Dataset, fmt: str, windows: bool) -> None:
    """Refuse, before anything is written, a dataset the format cannot hold so that its import
    gives it back: release windows where ``windows`` is False (D4RL and d3rlpy hold whole
    episodes), actions outside the action space (the format's readers and rlu's import take
    only actions in it), and discounts the format's terminal flags cannot express (a live
    discount other than 0 or 1, a 0 before an episode's last transition, or a last transition's
    discount that disagrees with the episode's terminal end). Streams the step columns."""
    start, length = np.asarray(ds.start), np.asarray(ds.length)
    if not len(start):
        raise RluError(f"{ds.path}: the dataset holds no segments; nothing to export")
    last = start + length - 1
    first_flag = np.asarray(ds.column("is_first"))[start]
    last_flag = np.asarray(ds.column("is_last"))[last]
    windows_n = int((~(first_flag & last_flag)).sum())
    if windows_n and not windows:
        i = int(np.flatnonzero(~(first_flag & last_flag))[0])
        raise RluError(
            f"{ds.path}: {windows_n} of its {len(start)} segments are release windows (segment "
            f"{i} starts or ends inside an episode); {fmt} files hold whole episodes, so the "
            "windows would come back as episodes: export it with --format minari, which keeps "
            "them, or convert the release's whole-episode files (the *_episodes families)"
        )
    seg_terminal = np.asarray(ds.column("is_terminal"))[last]
    action, discount = ds.column("action"), ds.column("discount")
    row = max(1, np.asarray(action[:1]).nbytes + 4)
    for a, b in iter_blocks(ds.num_steps, row):
        release_all(ds)
        steps = np.arange(a, b)
        seg = np.searchsorted(start, steps, side="right") - 1
        live = steps != last[seg]  # the final step's action and discount are no transition's
        lt = (steps == last[seg] - 1)[live]  # the segment's last transition
        tm = lt & seg_terminal[seg][live]
        bad = action_problem(ds.schema.action, np.asarray(action[a:b])[live])
        if bad is not None:
            step = a + int(np.flatnonzero(live)[bad[0]])
            raise RluError(
                f"{ds.path}: step {step}: {bad[1]}; {fmt} files are read by libraries (and by "
                "rlu's import) that take actions inside the action space, so the file would not "
                "come back: clip the actions first (rlu.data.store.DatasetWriter) if the env "
                "clipped them, or keep the dataset in rlu's store"
            )
        d = np.asarray(discount[a:b])[live]
        wrong = ~np.isin(d, (0.0, 1.0)) | ((d == 0) & ~lt) | (lt & ((d == 0) != tm))
        if wrong.any():
            step = a + int(np.flatnonzero(live)[int(np.flatnonzero(wrong)[0])])
            raise RluError(
                f"{ds.path}: step {step} has discount {float(discount[step])}; {fmt} files "
                "hold only terminal flags (discount 0 on an episode's last transition when it "
                "ends in a terminal state, 1 elsewhere), so this discount would not come back"
            )


# --- the sidecar ------------------------------------------------------------------------------
def _last_rows(ds: Dataset) -> tuple[np.ndarray, np.ndarray]:
    start, length = np.asarray(ds.start, np.int64), np.asarray(ds.length, np.int64)
    return start, start + length - 1


def _take(col: Any, rows: np.ndarray) -> np.ndarray:
    if isinstance(col, ZlibColumn):
        return col.take(rows)
    return np.asarray(col[rows]) if len(rows) else np.asarray(col[:0])


def attachments(ds: Dataset) -> list[str]:
    """The dataset's attached files (manifest paths under ``policies/``, ``source/``...)."""
    return sorted(r for r in ds.manifest["files"] if is_attachment(r))


def write_sidecar(
    ds: Dataset,
    out: Path,
    target: str,
    export_id: str,
    held: np.ndarray,
    skip_attachments: tuple[str, ...] = (),
) -> list[str]:
    """Write ``ds``'s sidecar at ``out`` atomically (module docstring); ``held`` marks the
    segments whose final observation the exported file lacks. Returns what it holds, for the
    export's one line."""
    from rlu.files import atomic_path

    start, last = _last_rows(ds)
    length = np.asarray(ds.length, np.int64)
    schema = ds.schema
    rels = [r for r in attachments(ds) if not r.startswith(skip_attachments)]
    info = {
        "format": SIDECAR_FORMAT,
        "version": SIDECAR_VERSION,
        "export_id": export_id,
        "target": target,
        "schema": schema.to_json(),
        "provenance": ds.manifest.get("provenance", {}),
        "attachments": rels,
    }
    held_rows = np.flatnonzero(held).astype(np.int64)
    per = 8 + 1 + 1 + 4 + 4 + 1 + np.dtype(schema.action.dtype).itemsize * schema.action.size
    per += sum(np.dtype(d).itemsize for d in METADATA_FIELDS.values())
    if len(length) * per > MAX_TABLE_BYTES:  # what read_sidecar would refuse: refused here first
        raise RluError(
            f"{ds.path}: {len(length):,} segments make a sidecar table of {len(length) * per:,} "
            f"bytes, more than the {MAX_TABLE_BYTES:,} rlu reads back; export fewer segments "
            "(release windows: convert the *_episodes files instead)"
        )
    with atomic_path(out, suffix=True) as tmp, NpzWriter(tmp) as w:
        w.add("rlu/sidecar", np.frombuffer(json.dumps(info, sort_keys=True).encode(), np.uint8))
        w.add("segments/length", length)
        w.add("segments/is_first", np.asarray(ds.column("is_first"))[start])
        w.add("segments/is_last", np.asarray(ds.column("is_last"))[last])
        w.add("segments/final_action", np.asarray(ds.column("action"))[last])
        w.add("segments/final_reward", np.asarray(ds.column("reward"))[last])
        w.add("segments/final_discount", np.asarray(ds.column("discount"))[last])
        w.add("segments/final_terminal", np.asarray(ds.column("is_terminal"))[last])
        for key in METADATA_FIELDS:
            w.add(f"segments/meta_{key}", np.asarray(ds.metadata(key)))
        w.add("segments/held_observation", held_rows)
        k = schema.frame_stack
        if k > 1:
            frame_start = np.asarray(ds.frame_start, np.int64)
            rows = frame_start[held_rows] + (k - 1) + length[held_rows] - 1
            _rows_member(w, "segments/final_observation", ds.column("observation"), rows)
            pre = (frame_start[held_rows][:, None] + np.arange(k - 1)[None]).reshape(-1)
            spec = cast(ArraySpec, schema.observation)  # Schema: frame_stack > 1 is one array
            with w.member(
                "segments/frame_prefix", (len(held_rows), k - 1, *spec.shape), spec.dtype
            ) as write:
                for a, b in iter_blocks(len(pre), max(1, spec.size)):
                    write(_take(ds.column("observation"), pre[a:b]))
        else:
            for name in schema.observation_columns():
                key = name.replace("observation", "segments/final_observation", 1)
                _rows_member(w, key, ds.column(name), last[held_rows])
        for rel in rels:
            path = ds.file(rel)
            size = os.path.getsize(path)
            with w.member(f"attachments/{rel}", (size,), np.uint8) as write, open(path, "rb") as fh:
                while block := fh.read(READ_BYTES):
                    write(np.frombuffer(block, np.uint8))
    what = ["each segment's final step and metadata", "the schema and provenance"]
    if len(held_rows):
        what.append(f"{len(held_rows)} final observation(s) the file lacks")
    if rels:
        what.append(f"{len(rels)} attached file(s) ({_describe(rels)})")
    return what


def _describe(rels: list[str]) -> str:
    kinds = sorted({r.split("/", 1)[0] for r in rels})
    return ", ".join(f"{k}/" for k in kinds)


def _rows_member(w: NpzWriter, key: str, col: Any, rows: np.ndarray) -> None:
    shape, dtype = tuple(col.shape[1:]), col.dtype
    with w.member(key, (len(rows), *shape), dtype) as write:
        for a, b in iter_blocks(len(rows), max(1, math.prod(shape) * np.dtype(dtype).itemsize)):
            write(_take(col, rows[a:b]))


@dataclasses.dataclass
class Sidecar:
    """A sidecar read back (its table in memory, its observations and attachments as
    columns read on demand), checked against the schema it declares."""

    path: Path
    info: dict[str, Any]
    schema: Schema
    table: dict[str, np.ndarray]
    held: dict[int, int]
    """Segment -> row of its final observation in the sidecar."""
    npz: NpzFile

    @property
    def segments(self) -> int:
        return len(self.table["length"])

    def close(self) -> None:
        self.npz.__exit__()


def find_sidecar(path: Path, export_id: str | None, where: str) -> Sidecar | None:
    """The sidecar at ``path`` if it exists and belongs to the file marked ``export_id``
    (None when the file carries no mark, or the sidecar is another export's: a warning)."""
    import warnings

    if export_id is None or not path.is_file():
        if export_id is not None:
            warnings.warn(
                f"{where} was exported by rlu, but its sidecar {path.name} is missing: the "
                "final steps, one-step segments, metadata, provenance and attachments it held "
                "are not restored (the file imports as its format's readers see it)",
                stacklevel=3,
            )
        return None
    sc = read_sidecar(path)
    if sc.info["export_id"] != export_id:
        sc.close()
        warnings.warn(
            f"{path} belongs to another export (id {sc.info['export_id']}, the file's is "
            f"{export_id}); it is ignored and the file imports as its format's readers see it",
            stacklevel=3,
        )
        return None
    return sc


def read_sidecar(path: Path) -> Sidecar:
    """Read and check a sidecar (a foreign file like any other: bounded, no pickle)."""
    from rlu.files import AnyJSON, ListOf, Record, Str, check_value

    fix = "export the dataset again (rlu export)"
    z = NpzFile(path, fix)
    try:
        if "rlu/sidecar" not in z.infos:
            raise FormatError(f"{path}: no 'rlu/sidecar' entry; not an rlu export's sidecar")
        raw = z.read("rlu/sidecar", MAX_SIDECAR_JSON)
        try:
            info = json.loads(raw.tobytes().decode("utf-8"))
        except (ValueError, UnicodeDecodeError, RecursionError) as e:
            raise FormatError(f"{path}: 'rlu/sidecar' is not JSON ({e}); {fix}") from None
        shape = Record(
            {
                "format": Str(max_len=64),
                "version": AnyJSON(),
                "export_id": Str(max_len=64),
                "target": Str(max_len=16),
                "schema": AnyJSON(),
                "provenance": AnyJSON(),
                "attachments": ListOf(Str(max_len=512), max_len=1 << 16),
            }
        )
        info = check_value(shape, info, f"{path}: 'rlu/sidecar'", fix)
        if info["format"] != SIDECAR_FORMAT or info["version"] != SIDECAR_VERSION:
            raise FormatError(
                f"{path}: a sidecar of format {info['format']!r} version {info['version']!r}; "
                f"this rlu reads {SIDECAR_FORMAT} version {SIDECAR_VERSION}: {fix}"
            )
        if not isinstance(info["provenance"], dict):
            raise FormatError(f"{path}: the sidecar's provenance is not an object; {fix}")
        try:
            schema = Schema.from_json(info["schema"])
        except FormatError as e:
            raise FormatError(f"{path}: the sidecar's {e}; {fix}") from None
        for rel in info["attachments"]:
            parts = Path(rel).parts
            if not is_attachment(rel) or ".." in parts or rel.startswith("/") or "\\" in rel:
                raise FormatError(f"{path}: attachment {rel!r} is not a path rlu attaches; {fix}")
            if f"attachments/{rel}" not in z.infos:
                raise FormatError(f"{path}: attachment {rel!r} is listed but missing; {fix}")
        table = _table(z, schema, path, fix)
        held_rows = table.pop("held_observation")
        held = {int(s): j for j, s in enumerate(held_rows.tolist())}
        return Sidecar(path, info, schema, table, held, z)
    except BaseException:
        z.__exit__()
        raise


def _table(z: NpzFile, schema: Schema, path: Path, fix: str) -> dict[str, np.ndarray]:
    act = schema.action
    want: dict[str, tuple[tuple[int, ...], str]] = {
        "length": ((), "int64"),
        "is_first": ((), "bool"),
        "is_last": ((), "bool"),
        "final_action": (tuple(act.shape), act.dtype),
        "final_reward": ((), "float32"),
        "final_discount": ((), "float32"),
        "final_terminal": ((), "bool"),
        **{f"meta_{k}": ((), d) for k, d in METADATA_FIELDS.items()},
    }
    out: dict[str, np.ndarray] = {}
    budget = MAX_TABLE_BYTES
    n = None
    for name, (shape, dtype) in want.items():
        key = f"segments/{name}"
        if key not in z.infos:
            raise FormatError(f"{path}: no {key!r} array; {fix}")
        m = z.member(key)
        if m.dtype != np.dtype(dtype) or tuple(m.shape[1:]) != shape or not m.shape:
            raise FormatError(
                f"{path}: {key!r} is {m.dtype}{list(m.shape)}; want {dtype} (S, {shape}); {fix}"
            )
        n = m.shape[0] if n is None else n
        if m.shape[0] != n:
            raise FormatError(f"{path}: {key!r} has {m.shape[0]} rows, 'segments/length' {n}")
        budget -= m.nbytes
        if budget < 0:
            raise FormatError(f"{path}: its segment table declares over {MAX_TABLE_BYTES} bytes")
        out[name] = z.read(key)
    if (out["length"] < 1).any():
        raise FormatError(f"{path}: a segment of fewer than 1 step; {fix}")
    held = z.read("segments/held_observation", MAX_TABLE_BYTES)
    if held.dtype.kind not in "iu" or held.ndim != 1:
        raise FormatError(f"{path}: 'segments/held_observation' is not a list of segments")
    if len(held) and (held.min() < 0 or held.max() >= (n or 0) or (np.diff(held) <= 0).any()):
        raise FormatError(f"{path}: 'segments/held_observation' names segments out of order")
    out["held_observation"] = held
    for name, spec in _final_obs_specs(schema).items():
        key = f"segments/{name}"
        if key not in z.infos:
            raise FormatError(f"{path}: no {key!r} array; {fix}")
        m = z.member(key)
        if m.dtype != np.dtype(spec.dtype) or m.shape != (len(held), *spec.shape):
            raise FormatError(
                f"{path}: {key!r} is {m.dtype}{list(m.shape)}; want {spec.dtype} "
                f"{[len(held), *spec.shape]}; {fix}"
            )
    return out


def _final_obs_specs(schema: Schema) -> dict[str, ArraySpec]:
    k = schema.frame_stack
    if k > 1:
        spec = cast(ArraySpec, schema.observation)  # Schema: frame_stack > 1 is one array
        return {
            "final_observation": spec,
            "frame_prefix": ArraySpec((k - 1, *spec.shape), spec.dtype),
        }
    return {
        n.replace("observation", "final_observation", 1): s
        for n, s in schema.observation_columns().items()
    }


class _HeldReader:
    """The sidecar's final observations, read front to back a row at a time."""

    def __init__(self, sc: Sidecar):
        self.cols: dict[str, Column] = {
            name: sc.npz.column(f"segments/{name}") for name in _final_obs_specs(sc.schema)
        }

    def row(self, j: int) -> dict[str, np.ndarray]:
        return {name: c.rows(j, j + 1)[0] for name, c in self.cols.items()}


def restore(segments: Iterator[Segment], sc: Sidecar, where: str) -> Iterator[Segment]:
    """The segments of rlu's export as rlu wrote them: ``segments`` are the file's episodes
    (the format's view), merged with the sidecar's final steps, one-step segments, flags and
    metadata. A file whose episodes disagree with its sidecar is refused."""
    t = sc.table
    reader = _HeldReader(sc)
    fix = "the file was changed after rlu exported it: export the dataset again"
    it = iter(segments)
    for i in range(sc.segments):
        length = int(t["length"][i])
        held = reader.row(sc.held[i]) if i in sc.held else None
        if length == 1:
            if held is None:
                raise FormatError(f"{sc.path}: one-step segment {i} has no final observation")
            seg = _one_step(sc, i, held)
        else:
            try:
                seg = next(it)
            except StopIteration:
                raise FormatError(
                    f"{where}: holds fewer episodes than its sidecar {sc.path.name} "
                    f"({sc.segments} segments); {fix}"
                ) from None
            if len(seg) != length or bool(seg.is_terminal[-1]) != bool(t["final_terminal"][i]):
                raise FormatError(
                    f"{where}: episode of segment {i} has {len(seg)} steps "
                    f"({'terminal' if seg.is_terminal[-1] else 'truncated'}); its sidecar says "
                    f"{length} ({'terminal' if t['final_terminal'][i] else 'truncated'}); {fix}"
                )
            seg = _final_step(seg, sc, i, held)
        yield seg
    if next(it, None) is not None:
        raise FormatError(
            f"{where}: holds more episodes than its sidecar {sc.path.name} ({sc.segments}); {fix}"
        )


def _meta(sc: Sidecar, i: int) -> dict[str, Any]:
    out = {}
    for key, dtype in METADATA_FIELDS.items():
        v = sc.table[f"meta_{key}"][i]
        missing = METADATA_MISSING[dtype]
        if not (v == missing or (isinstance(missing, float) and np.isnan(v))):
            out[key] = v.item()
    return out


def _final_step(seg: Segment, sc: Sidecar, i: int, held: dict | None) -> Segment:
    t = sc.table
    action, reward, discount = seg.action.copy(), seg.reward.copy(), seg.discount.copy()
    action[-1] = t["final_action"][i]
    reward[-1] = t["final_reward"][i]
    discount[-1] = t["final_discount"][i]
    is_first, is_last = seg.is_first.copy(), seg.is_last.copy()
    is_first[0], is_last[-1] = t["is_first"][i], t["is_last"][i]
    obs, prefix = seg.observation, seg.frame_prefix
    if held is not None:
        if sc.schema.frame_stack > 1:
            obs = np.array(obs)
            obs[-1] = held["final_observation"]
        else:
            obs = _with_last(obs, held)
    return dataclasses.replace(
        seg,
        observation=obs,
        action=action,
        reward=reward,
        discount=discount,
        is_first=is_first,
        is_last=is_last,
        metadata=_meta(sc, i),
        frame_prefix=prefix,
    )


def _with_last(obs: Any, held: dict[str, np.ndarray]) -> Any:
    if isinstance(obs, Mapping):
        out = {k: np.array(v) for k, v in obs.items()}
        for k in out:
            out[k][-1] = held[f"final_observation/{k}"]
        return out
    obs = np.array(obs)
    obs[-1] = held["final_observation"]
    return obs


def _one_step(sc: Sidecar, i: int, held: dict[str, np.ndarray]) -> Segment:
    t, schema = sc.table, sc.schema
    prefix = None
    if schema.frame_stack > 1:
        obs: Any = held["final_observation"][None]
        prefix = held["frame_prefix"]
    elif isinstance(schema.observation, Mapping):
        obs = {k: held[f"final_observation/{k}"][None] for k in schema.observation}
    else:
        obs = held["final_observation"][None]
    return Segment(
        observation=obs,
        action=t["final_action"][i : i + 1].copy(),
        reward=t["final_reward"][i : i + 1].copy(),
        discount=t["final_discount"][i : i + 1].copy(),
        is_first=t["is_first"][i : i + 1].copy(),
        is_last=t["is_last"][i : i + 1].copy(),
        is_terminal=t["final_terminal"][i : i + 1].copy(),
        metadata=_meta(sc, i),
        frame_prefix=prefix,
    )


def attach_from_sidecar(w: DatasetWriter, sc: Sidecar, folder: Path) -> None:
    """Attach the sidecar's files to the dataset being written (each streamed through an
    anonymous temporary in ``folder``)."""
    for rel in sc.info["attachments"]:
        m = sc.npz.member(f"attachments/{rel}")
        if m.dtype != np.uint8 or len(m.shape) != 1 or m.nbytes > MAX_ATTACHMENT_BYTES:
            raise FormatError(f"{sc.path}: attachment {rel!r} is not a file's bytes")
        col = sc.npz.column(f"attachments/{rel}")
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".rlu-attach-")
        try:
            with os.fdopen(fd, "wb") as fh:
                for a, b in iter_blocks(m.shape[0], 1):
                    fh.write(col.rows(a, b).tobytes())
            w.attach(rel, tmp)
        finally:
            os.unlink(tmp)


def restored_schema(sc: Sidecar, schema: Schema | None, where: str) -> Schema:
    """The sidecar's schema, which must store what ``schema`` (the task's, when given) does."""
    if schema is not None:
        a, b = dict(sc.schema.to_json()), dict(schema.to_json())
        a.pop("image_encoding"), b.pop("image_encoding")
        a_obs = a.pop("observation")
        b_obs = b.pop("observation")
        if a != b or (a_obs != b_obs and schema.task_id and schema.task_id != sc.schema.task_id):
            raise RluError(
                f"{where}: exported by rlu from a dataset of task {sc.schema.task_id}; import it "
                f"with --task {sc.schema.task_id} (or without --task)"
            )
    return sc.schema


# --- a foreign file's extras: source/<format>.json + .npz --------------------------------------
def source_json_name(fmt: str) -> str:
    return f"source/{fmt}.json"


def source_npz_name(fmt: str) -> str:
    return f"source/{fmt}.npz"


class SourceWriter:
    """Gathers what an import keeps of a foreign file (``source/<fmt>.json`` and ``.npz``) and
    attaches both to the dataset being written. Arrays stream into a temporary .npz in the
    destination's folder, a block at a time."""

    def __init__(self, fmt: str, folder: Path):
        self.fmt = fmt
        self.info: dict[str, Any] = {"format": fmt, "arrays": {}}
        self._folder = folder
        self._spools: dict[str, _Spool] = {}
        self._fd, self._tmp = tempfile.mkstemp(dir=folder, prefix=".rlu-source-", suffix=".npz")
        os.close(self._fd)
        self.npz = NpzWriter(self._tmp)

    def add(self, key: str, a: Any) -> str:
        a = np.asarray(a)
        self.npz.add(key, a)
        self.info["arrays"][key] = {"shape": list(a.shape), "dtype": a.dtype.name}
        return key

    def column(self, key: str, col: Column, where: str) -> str:
        """Copy column ``col`` (rows read a block at a time) as array ``key``."""
        shape = tuple(col.shape)
        with self.npz.member(key, shape, col.dtype) as write:
            if shape:
                for a, b in iter_blocks(shape[0], max(1, col.row_bytes)):
                    write(col.rows(a, b))
            else:
                write(col.rows(0, 1))
        self.info["arrays"][key] = {"shape": list(shape), "dtype": np.dtype(col.dtype).name}
        return key

    def spool(self, key: str, dtype: Any, row_shape: tuple[int, ...]) -> _Spool:
        """Rows of array ``key`` appended as they come (an anonymous temporary holds them until
        :meth:`attach` writes the array)."""
        if key not in self._spools:
            self._spools[key] = _Spool(self._folder, np.dtype(dtype), tuple(row_shape))
        return self._spools[key]

    def attach(self, w: DatasetWriter) -> None:
        from rlu.files import write_atomic

        for key, sp in self._spools.items():
            shape = (sp.rows, *sp.row_shape)
            with self.npz.member(key, shape, sp.dtype) as write:
                sp.fh.seek(0)
                row = max(1, math.prod(sp.row_shape) * sp.dtype.itemsize)
                for a, b in iter_blocks(sp.rows, row):
                    data = sp.fh.read((b - a) * row)
                    write(np.frombuffer(data, sp.dtype).reshape(b - a, *sp.row_shape))
            self.info["arrays"][key] = {"shape": list(shape), "dtype": sp.dtype.name}
            sp.fh.close()
        self._spools.clear()
        self.npz.zf.close()
        w.attach(source_npz_name(self.fmt), self._tmp)
        text = json.dumps(self.info, sort_keys=True, allow_nan=False)
        jtmp = self._tmp + ".json"
        write_atomic(jtmp, text)
        try:
            w.attach(source_json_name(self.fmt), jtmp)
        finally:
            os.unlink(jtmp)

    def close(self) -> None:
        for sp in self._spools.values():
            sp.fh.close()
        with contextlib.suppress(Exception):
            self.npz.zf.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self._tmp)


class _Spool:
    def __init__(self, folder: Path, dtype: np.dtype, row_shape: tuple[int, ...]):
        self.fh = tempfile.TemporaryFile(dir=folder)
        self.dtype, self.row_shape, self.rows = dtype, row_shape, 0

    def append(self, rows: Any) -> None:
        a = np.asarray(rows)
        if a.dtype != self.dtype or tuple(a.shape[1:]) != self.row_shape:
            raise RluError(f"rows of {a.dtype}{list(a.shape[1:])} for a spool of {self.dtype}")
        self.fh.write(np.ascontiguousarray(a).tobytes())
        self.rows += len(a)


def read_source(ds: Dataset, fmt: str) -> tuple[dict[str, Any], NpzFile] | None:
    """What an import kept of its ``fmt`` file (``source/<fmt>.json``, and the .npz open), or
    None when the dataset was not imported from one."""
    from rlu.files import AnyJSON, MapOf, Record, check_value

    rel = source_json_name(fmt)
    if rel not in ds.manifest["files"]:
        return None
    fix = "re-import the file"
    path = ds.file(rel)
    from rlu.files import read_bytes

    raw = read_bytes(path, MAX_SOURCE_JSON, fix)
    try:
        info = json.loads(raw.decode("utf-8"))
    except (ValueError, UnicodeDecodeError, RecursionError) as e:
        raise FormatError(f"{path}: not JSON ({e}); {fix}") from None
    info = check_value(
        Record({"format": AnyJSON(), "arrays": MapOf(AnyJSON(), max_len=1 << 20)}),
        info,
        str(path),
        fix,
    )
    if info["format"] != fmt:
        raise FormatError(f"{path}: field 'format' is {info['format']!r}, not {fmt!r}; {fix}")
    return info, NpzFile(ds.file(source_npz_name(fmt)), fix)
