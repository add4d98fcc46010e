"""Release shards -> the native store, streaming and parallel over shards.

Worker processes (one per core by default) read and decode shards (inflate, CRC, Example, PNG,
and the deflating of image columns the store compresses: the CPU-heavy part) and hand batches of
columns to the parent through one queue per shard, at most ``_QUEUE_MIB`` queued per reader; the
parent only appends them to one :class:`~rlu.data.store.DatasetWriter` in shard order, so the
output is the same bytes for any number of workers. Atari transitions convert 1.8-1.95x faster with
2 workers than in one process, control-suite windows 1.2-1.3x (bench/release_reader.py). Any
failure (a damaged shard, a schema mismatch, Ctrl-C) aborts the writer: nothing is left at
``out``.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import re
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data.release.families import get_family, iter_segments, reader_for
from rlu.data.store import DatasetWriter, Deflated, Schema, SegmentColumns, segment_columns
from rlu.domains import DOMAINS
from rlu.progress import Progress
from rlu.segments import METADATA_FIELDS, SegmentBatch
from rlu.system import available_cores
from rlu.tasks import TaskSpec, get_task, rwrl_observation_spec
from rlu.types import ArraySpec, DiscreteSpec, FormatError, RluError, SpecError
from rlu.workers import die_with_parent

_RUN_RE = re.compile(r"run_(\d+)")
_QUEUE_MIB = 256  # decoded data a reader may hold queued ahead of the parent


@dataclass
class ConvertReport:
    out: Path
    segments: int = 0
    steps: int = 0
    records: int = 0
    skipped: int = 0
    files: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0


def schema_for(
    task: TaskSpec, family: str, challenge: str | None = None, image_encoding: str | None = None
) -> Schema:
    """The store schema of a task's release family (Atari transitions keep their 4-frame stacks)."""
    fam = get_family(family)
    if image_encoding is None:
        image_encoding = fam.image_encoding
    if fam.whole_stacks:
        return Schema.for_task(task, image_encoding, observation=task.observation_spec)
    if DOMAINS[task.domain].challenges:
        return Schema.for_task(
            task, image_encoding, observation=rwrl_observation_spec(task, challenge or "none")
        )
    return Schema.for_task(task, image_encoding)


def _fit(batch: SegmentBatch, schema: Schema, where: str) -> SegmentBatch:
    """Keep the schema's observation keys (files hold extra ones), cast dtypes, check shapes."""
    spec = schema.observation
    obs = batch.observation
    if isinstance(spec, Mapping):
        if not isinstance(obs, Mapping):
            raise SpecError(f"{where}: the file holds one observation array, the task a dict")
        missing = sorted(set(spec) - set(obs))
        if missing:
            raise SpecError(
                f"{where}: observation keys {missing} of the task are not in the file (it has "
                f"{sorted(obs)}); is --task right for these files?"
            )
        obs = {k: _cast(obs[k], spec[k], f"{where}: observation {k!r}") for k in spec}
    else:
        if isinstance(obs, Mapping):
            raise SpecError(f"{where}: the file holds a dict observation, the task one array")
        obs = _cast(obs, spec, f"{where}: observation")
    action = _cast(batch.action, schema.action, f"{where}: action")
    if isinstance(schema.action, DiscreteSpec) and action.size:
        _check_action_ids(action, batch.action, schema.action.num_values, where)
    return SegmentBatch(
        obs,
        action,
        batch.reward,
        batch.discount,
        batch.is_first,
        batch.is_last,
        batch.is_terminal,
        batch.metadata,
        batch.lengths,
    )


def _check_action_ids(action: np.ndarray, stored: np.ndarray, n: int, where: str) -> None:
    """Discrete actions are ids 0..n-1 of the task's action set; one outside it would index
    past an agent's Q-values, so the file is refused here, not at the first batch holding it."""
    lo, hi = int(action.min()), int(action.max())
    if lo < 0 or hi >= n:
        bad = int(np.flatnonzero((action < 0) | (action >= n))[0])
        seg, step = np.unravel_index(bad, action.shape[:2]) if action.ndim >= 2 else (bad, 0)
        raise SpecError(
            f"{where}: action {int(stored.reshape(-1)[bad])} (segment {int(seg)}, step "
            f"{int(step)}) is outside the task's {n} actions (0 to {n - 1}); is --task right "
            "for these files?"
        )


def _cast(v: np.ndarray, spec: ArraySpec, what: str) -> np.ndarray:
    if tuple(v.shape[2:]) != tuple(spec.shape):
        raise SpecError(
            f"{what} has per-step shape {tuple(v.shape[2:])}; the task wants {tuple(spec.shape)}"
        )
    return v.astype(spec.dtype, copy=False)


def _with_meta(batch: SegmentBatch, meta: Mapping[str, Any]) -> SegmentBatch:
    n = len(batch)
    md = dict(batch.metadata)
    for k, v in meta.items():
        md.setdefault(k, np.full(n, v, METADATA_FIELDS[k]))
    batch.metadata = md
    return batch


def fast_path(batch: SegmentBatch, schema: Schema) -> bool:
    """Whether ``batch`` appends as whole columns (else segment by segment)."""
    return batch.lengths is None and schema.frame_stack == 1 and len(batch) > 1


def batch_columns(batch: SegmentBatch, schema: Schema, deflate: bool = False) -> SegmentColumns:
    """Flatten a fast-path batch (:func:`fast_path`) into the store's columns.

    ``deflate``: compress the columns the store keeps as zlib here, one thread (for readers).
    """
    n, t = len(batch), batch.reward.shape[1]
    segment_columns(schema, next(iter(batch)))  # keys, shapes and dtypes, the store's messages
    flat = lambda a: np.asarray(a).reshape(n * t, *np.asarray(a).shape[2:])  # noqa: E731
    cols: dict[str, Any] = {}
    if isinstance(batch.observation, Mapping):
        cols.update({f"observation/{k}": flat(v) for k, v in batch.observation.items()})
    else:
        cols["observation"] = flat(batch.observation)
    cols.update(
        action=flat(batch.action),
        reward=flat(batch.reward),
        discount=flat(batch.discount),
        is_first=flat(batch.is_first),
        is_last=flat(batch.is_last),
        is_terminal=flat(batch.is_terminal),
    )
    if deflate:
        for name, spec in schema.step_columns().items():
            if schema.encoding(spec) == "zlib":
                cols[name] = Deflated.of(cols[name], spec.dtype, threaded=False)
    return SegmentColumns(cols, np.full(n, t, np.int64), dict(batch.metadata))


def append_batch(writer: DatasetWriter, batch: SegmentBatch) -> None:
    """Append N segments at once (the column files get one write each).

    Equivalent to ``writer.append`` per segment (``tests/release/test_convert.py`` checks the
    bytes); trimmed batches and frame-stacked schemas are joined segment by segment first.
    """
    if len(batch) == 0:
        return
    if fast_path(batch, writer.schema):
        writer.append_columns(batch_columns(batch, writer.schema))
    else:
        writer.extend(batch)


# --- workers -------------------------------------------------------------------------------


def shard_batches(
    job: ShardJob, path: str, columns: bool = False
) -> Iterator[tuple[SegmentBatch | SegmentColumns | None, dict[str, Any] | None]]:
    """One shard decoded, in order: ``(batch, None)``... then ``(None, stats)``; the batches
    fitted to the schema, one decode batch held at a time (at most 64 MiB of records; 64 Atari
    transitions, 4 Atari or DMLab episodes), never the shard.

    ``columns``: fast-path batches come as :class:`SegmentColumns` with image columns deflated
    in this thread (what a reader process or a cluster's shard job makes: whoever writes them
    then only writes bytes). ``stats``: the shard's ``path``, ``records``, ``skipped``,
    ``errors`` (the first 20) and ``bytes``.
    """
    reader = reader_for(path, job.family, verify=job.verify, on_error=job.on_error)
    for segments in iter_segments(path, job.family, reader=reader, on_error=job.on_error):
        batch = _with_meta(_fit(segments, job.schema, path), job.meta)
        if columns and fast_path(batch, job.schema):
            yield batch_columns(batch, job.schema, deflate=True), None
        else:
            yield batch, None
    if reader.stats.records == 0 and reader.stats.skipped == 0:
        raise FormatError(
            f"{path}: holds no records (an empty or foreign file); a release shard holds at "
            "least one: download it again"
        )
    yield (
        None,
        {
            "path": path,
            "records": reader.stats.records,
            "skipped": reader.stats.skipped,
            "errors": reader.stats.errors[:20],
            "bytes": os.path.getsize(path),
        },
    )


def write_batch(writer: DatasetWriter, batch: SegmentBatch | SegmentColumns) -> None:
    """Append one batch of :func:`shard_batches` to ``writer``."""
    if isinstance(batch, SegmentColumns):
        writer.append_columns(batch)
    else:
        append_batch(writer, batch)


@dataclass(frozen=True)
class ShardJob:
    """How every shard of one dataset is decoded (the same for each of its shards)."""

    family: str
    """The release family of the files."""
    schema: Schema
    """The dataset's store schema (:func:`schema_for`)."""
    meta: Mapping[str, Any]
    """Segment metadata every segment gets where the file has none (the Atari run)."""
    verify: bool
    """Check every record's CRCs."""
    on_error: str
    """``raise`` at the first damaged record, or ``skip`` it and count it."""


@dataclass(frozen=True)
class ConvertPlan:
    """What :func:`plan_conversion` settled for one dataset: how its shards decode and the
    provenance it gets (before the shards' own entries, :func:`record_shards`)."""

    task: TaskSpec
    job: ShardJob
    provenance: Mapping[str, Any]


def plan_conversion(
    paths: Sequence[str],
    family: str,
    task_id: str,
    *,
    challenge: str | None = None,
    run: str | int | None = None,
    verify: bool = True,
    on_error: str = "raise",
    image_encoding: str | None = None,
    provenance: Mapping[str, Any] | None = None,
    check_files: bool = True,
) -> ConvertPlan:
    """Every check of a conversion that needs no byte of the files (the family belongs to the
    task, an RWRL challenge is given, the files exist unless ``check_files`` is False: a
    cluster job's shards still to be downloaded), then how its shards decode and its
    provenance."""
    get_family(family)
    task = get_task(task_id)
    task.release_dataset(family)  # the family must belong to the task
    if DOMAINS[task.domain].challenges and challenge is None:
        raise RluError(f"{task.id}: say which challenge the files are from: --challenge none|easy")
    if not paths:
        raise RluError("no shard files to convert; give FILE... or --src ROOT")
    for p in paths if check_files else ():
        if not os.path.isfile(p):
            raise RluError(f"{p}: no such shard file")
    schema = schema_for(task, family, challenge, image_encoding)
    meta: dict[str, Any] = {}
    kind = DOMAINS[task.domain].datasets
    if kind == "runs":
        r = run if run is not None else _run_from_names(paths)
        if r is not None:
            meta["run"] = int(str(r).removeprefix("run_"))
    named_run = _run_folder(task, paths, run) if kind == "run_names" else None
    prov = {
        "source": "rl_unplugged release",
        "family": family,
        **({"reward": note} if (note := get_family(family).reward_note) is not None else {}),
        "task": task.id,
        "challenge": challenge,
        "run": meta.get("run", named_run),
        "code_version": _version(),
        **(provenance or {}),
    }
    return ConvertPlan(task, ShardJob(family, schema, meta, verify, on_error), prov)


def record_shards(provenance: dict[str, Any], stats: Sequence[Mapping[str, Any]]) -> None:
    """The dataset's provenance gets each shard's name, bytes, records and skipped records, in
    shard order (``stats`` as :func:`shard_batches` reports them)."""
    provenance["files"] = [
        {
            "name": os.path.basename(f["path"]),
            "bytes": f["bytes"],
            "records": f["records"],
            "skipped": f["skipped"],
        }
        for f in stats
    ]
    provenance["skipped_records"] = sum(f["skipped"] for f in stats)


def _nbytes(x: Any) -> int:
    """Bytes of the arrays in a batch (what it costs to hold it queued)."""
    if isinstance(x, np.ndarray):
        return x.nbytes
    if isinstance(x, Deflated):
        return len(x.data)
    if isinstance(x, Mapping):
        return sum(_nbytes(v) for v in x.values())
    if isinstance(x, (list, tuple)):
        return sum(_nbytes(v) for v in x)
    return _nbytes(vars(x)) if hasattr(x, "__dict__") else 0


def _worker(job: ShardJob, path: str, q: Any, budget: Any, parent: int) -> None:
    """Read one shard into ``q``, holding at most ``_QUEUE_MIB`` queued (``budget``: MiB units).

    The bound is in bytes, not batches, so a reader of a later shard can get far ahead (whole
    shards of windows) while the parent writes the earlier one: readers overlap each other.
    """
    die_with_parent(parent)
    try:
        for batch, stats in shard_batches(job, path, columns=True):
            if stats is not None:
                q.put(("done", stats))
                continue
            units = min(_QUEUE_MIB, max(1, -(-_nbytes(batch) // (1 << 20))))
            for _ in range(units):
                budget.acquire()
            q.put(("batch", (units, batch)))
    except RluError as e:
        q.put(("error", (type(e).__name__, str(e))))
    except BaseException as e:  # reported to the parent, which aborts the dataset
        q.put(("error", ("Error", f"{path}: {type(e).__name__}: {e}")))


class _Pool:
    """Up to ``workers`` shard readers running ahead of the parent, each with its own queue."""

    def __init__(self, files: Sequence[str], job: ShardJob, workers: int):
        fork = "fork" in mp.get_all_start_methods()
        self.ctx = mp.get_context("fork") if fork else mp.get_context("spawn")
        self.files, self.job, self.workers = files, job, workers
        self.procs: dict[int, Any] = {}
        self.queues: dict[int, Any] = {}
        self.budgets: dict[int, Any] = {}
        self.next = 0

    def _start_upto(self, i: int) -> None:
        while self.next < len(self.files) and self.next <= i:
            q, budget = self.ctx.Queue(), self.ctx.Semaphore(_QUEUE_MIB)
            p = self.ctx.Process(
                target=_worker,
                args=(self.job, self.files[self.next], q, budget, os.getpid()),
                daemon=True,
            )
            p.start()
            self.procs[self.next], self.queues[self.next] = p, q
            self.budgets[self.next] = budget
            self.next += 1

    def shard(
        self, i: int
    ) -> Iterator[tuple[SegmentBatch | SegmentColumns | None, dict[str, Any] | None]]:
        self._start_upto(i + self.workers - 1)
        q, p = self.queues[i], self.procs[i]
        while True:
            try:
                kind, payload = q.get(timeout=1.0)
            except queue.Empty:
                if not p.is_alive() and q.empty():
                    raise RluError(
                        f"{self.files[i]}: the reader process died (exit code {p.exitcode}); "
                        "out of memory? Try --workers 1"
                    ) from None
                continue
            if kind == "batch":
                units, batch = payload
                for _ in range(units):
                    self.budgets[i].release()
                yield batch, None
            elif kind == "done":
                yield None, payload
                break
            else:
                name, msg = payload
                if name == "SpecError":
                    raise SpecError(msg)
                raise FormatError(msg) if name != "Error" else RluError(msg)
        p.join()
        del self.procs[i], self.queues[i], self.budgets[i]

    def close(self) -> None:
        for p in self.procs.values():
            if p.is_alive():
                p.terminate()
            p.join()
        self.procs.clear()


def convert(
    files: Sequence[str | os.PathLike],
    family: str,
    task_id: str,
    out: str | os.PathLike,
    *,
    challenge: str | None = None,
    run: str | int | None = None,
    workers: int | None = None,
    verify: bool = True,
    on_error: str = "raise",
    image_encoding: str | None = None,
    overwrite: bool = False,
    progress: bool = False,
    provenance: Mapping[str, Any] | None = None,
) -> ConvertReport:
    """Convert release shard files of one family into a new dataset at ``out``.

    ``progress``: show an :class:`rlu.progress.Progress` on stderr (a bar on a terminal, a line
    every 10 s elsewhere) over the shards' bytes, with shards, steps and episodes so far.
    """
    paths = [os.fspath(f) for f in files]
    plan = plan_conversion(
        paths,
        family,
        task_id,
        challenge=challenge,
        run=run,
        verify=verify,
        on_error=on_error,
        image_encoding=image_encoding,
        provenance=provenance,
    )
    job, schema = plan.job, plan.job.schema
    workers = workers if workers is not None else min(available_cores(), len(paths), 8)
    report = ConvertReport(Path(out))
    t0 = time.monotonic()
    prov = dict(plan.provenance)
    # ``workers`` reader processes: the parent only appends decoded batches (and deflates image
    # columns in threads), so it shares a core with a reader rather than taking one.
    pool = _Pool(paths, job, workers) if workers > 1 else None
    sizes = [os.path.getsize(p) for p in paths]
    bar = Progress(sum(sizes), "convert", "B", quiet=not progress)
    ok = False
    try:
        with DatasetWriter(out, schema, provenance=prov, overwrite=overwrite) as writer:
            for i, path in enumerate(paths):
                stream = pool.shard(i) if pool else shard_batches(job, path)
                for batch, stats in stream:
                    if stats is not None:
                        report.files.append(stats)
                        report.records += stats["records"]
                        report.skipped += stats["skipped"]
                        continue
                    assert batch is not None  # a pair holds a batch or the stats
                    write_batch(writer, batch)
                    bar.set_postfix(
                        shards=f"{i}/{len(paths)}",
                        steps=writer.num_steps,
                        episodes=writer.num_episodes,
                    )
                bar.update(sizes[i])
                bar.set_postfix(
                    shards=f"{i + 1}/{len(paths)}",
                    steps=writer.num_steps,
                    episodes=writer.num_episodes,
                )
            record_shards(writer.provenance, report.files)
            report.segments = writer.num_segments
            report.steps = writer.num_steps
        ok = True
    finally:
        if pool is not None:
            pool.close()
        bar.close(failed=not ok)
    report.seconds = time.monotonic() - t0
    return report


def _run_from_names(paths: Sequence[str]) -> int | None:
    runs = {m.group(1) for p in paths if (m := _RUN_RE.search(os.path.basename(p)))}
    return int(runs.pop()) if len(runs) == 1 else None


def _run_folder(task: TaskSpec, paths: Sequence[str], run: str | int | None) -> str | None:
    """A named run (DMLab's ``training_0``): ``run`` if given, else the folder all the shards
    are in when it is one of the task's runs (``dmlab/<level>/<run>/tfrecord-...``)."""
    if run is not None:
        if str(run) not in task.datasets:
            raise RluError(
                f"{task.id}: no released run {run!r}; use one of {', '.join(task.datasets)}"
            )
        return str(run)
    folders = {os.path.basename(os.path.dirname(os.path.abspath(p))) for p in paths}
    folder = folders.pop() if len(folders) == 1 else None
    return folder if folder in task.datasets else None


def _version() -> str:
    import rlu

    return rlu.__version__
