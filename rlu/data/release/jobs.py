"""Many release datasets at once, one job per shard, on the one runner (local processes or a Ray
cluster): what ``rlu download`` and ``rlu convert`` do with ``--backend ray``, ``--out-root`` or
``--download``.

The unit of work is a shard. A shard job (:func:`run_shard`) downloads its file into the cache
(``--download``: fetched or reused, verified either way) or reads it where it lies, and decodes it
into a *part*: a complete rlu dataset of that shard alone, written under a name of its own and
renamed into place once whole, so a part exists whole or not at all. Once every shard of a
dataset has its part, one assembly job (:func:`assemble`) appends the parts in shard order
(:meth:`rlu.data.store.DatasetWriter.append_dataset`: bytes copied, zlib offsets and the segment
index shifted, every part's sha256 checked on the way) into the dataset, atomically, and removes
the parts. The dataset is the same bytes as the local conversion (:func:`convert`, or
``load_dataset(source="release")`` for ``--download``) for any number of nodes and workers.

- **Storage.** Every node reads the shards and writes the parts and the datasets through one
  folder that all of them see at the same path: a POSIX shared filesystem (NFS, Lustre, EFS,
  CephFS, GPFS), or one machine's disk when the cluster is that machine. Object-store URLs
  (``s3://``, ``gs://``) are not paths and are refused; a node-local disk on a multi-node
  cluster cannot work (a part written on one node is missing on the node that assembles).
  Renames must be atomic and ``flock`` must work there (NFSv4 and Lustre mounted with
  ``flock`` do).
- **Lost nodes.** A shard job whose node dies is run again by Ray (``retries``). Two attempts of
  one shard may overlap (the first one on a node that is dying): each writes a part of its own
  and the first rename wins; both are the same bytes, since a part depends only on its inputs.
  A retried download waits for the cache entry's lock its first attempt held (``LOCK_WAIT``).
- **Resume.** A part whose manifest records the same inputs (rlu version, family, schema, the
  shard's name, size and sha256 or modification time) and whose files match their sha256 is
  reused: an interrupted job, run again, converts only the shards without a part. A dataset
  already there is left as it is (``overwrite=True`` rebuilds it).
- **Memory.** A shard job holds one decode batch (at most 64 MiB of records; 64 Atari
  transitions; 4 Atari or DMLab episodes) and its decoded arrays, never the shard: an Atari
  episode shard of 1M frames streams through, 4 episodes of frames at a time (bench/README.md
  measures the peak). Assembly copies in 8 MiB blocks.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
import time
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rlu.data.release.convert import (
    ShardJob,
    plan_conversion,
    record_shards,
    shard_batches,
    write_batch,
)
from rlu.data.release.download import Downloader, Fetched, release_dir
from rlu.data.release.families import get_family
from rlu.data.store import MANIFEST, DatasetWriter, Schema, read_manifest, verify_checksums
from rlu.files import check_output, move_into_place
from rlu.progress import Progress, format_duration, format_size
from rlu.types import FormatError, RluError
from rlu.workers import Backend, node_name, run_jobs, send

LOCK_WAIT = 600.0
"""Seconds a shard's download waits for a cache entry another attempt holds: a first attempt
lost with its node holds it until its process dies (at once on one machine; an NFS server
drops a dead client's locks after its lease, 90 s by default)."""
_SEND_EVERY = 8 << 20  # bytes between two progress messages of one job
_URL_SCHEMES = ("s3://", "gs://", "gcs://", "az://", "abfs://", "http://", "https://", "hdfs://")


@dataclass(frozen=True)
class Fetch:
    """How a job's shard jobs download their files (``rlu convert --download``)."""

    cache_dir: str
    """The cache every node shares: shards land in ``CACHE/release/<object>``."""
    base_url: str | None = None
    """A mirror of the bucket (default: the public bucket)."""
    retries: int = 5
    """Tries of one file after the first."""
    timeout: float = 30.0
    """Seconds a connection may stay silent."""
    allow_redirects: bool = False
    """Follow redirects to other hosts."""

    def downloader(self) -> Downloader:
        return Downloader(
            cache_dir=self.cache_dir,
            base_url=self.base_url,
            workers=1,
            retries=self.retries,
            timeout=self.timeout,
            progress=False,
            allow_redirects=self.allow_redirects,
            lock_wait=LOCK_WAIT,
        )


@dataclass(frozen=True)
class DatasetJob:
    """One dataset to make: the shards of one task's (run / challenge / size) dataset."""

    task: str
    """The task id."""
    family: str
    """The release family."""
    out: str
    """The dataset's folder (on the shared storage)."""
    shards: tuple[str, ...]
    """The shard files in shard order, or with a :class:`Fetch` the bucket objects."""
    dataset: str = ""
    """The release dataset (``run_1``, ``none/large``; '' for a task with one)."""
    challenge: str | None = None
    """RWRL: the combined challenge of the files."""
    run: str | None = None
    """Atari: the run of the files (default: read from their names)."""
    provenance: Mapping[str, Any] = field(default_factory=dict)
    """More provenance for the dataset's manifest (the local conversion's ``provenance``)."""


@dataclass(frozen=True)
class ShardResult:
    """What one shard job did."""

    dataset: int
    index: int
    stats: Mapping[str, Any]
    """The shard's ``path``, ``records``, ``skipped``, ``errors``, ``bytes``."""
    part: str
    part_bytes: int
    reused: bool
    """The part was there from an earlier run and verified."""
    node: str
    """Where it ran (:func:`rlu.workers.node_name`)."""
    seconds: float
    sha256: str | None = None
    """The shard file's sha256 when it was downloaded (or reused from the cache)."""
    object: str | None = None


@dataclass
class DatasetReport:
    out: str
    task: str
    family: str
    dataset: str
    shards: int
    status: str = "pending"
    """``converted``, ``existed`` (left as it was), or ``pending`` (not assembled: the job
    stopped)."""
    segments: int = 0
    steps: int = 0
    episodes: int = 0
    bytes: int = 0
    reused: int = 0
    skipped_records: int = 0


@dataclass
class JobReport:
    """A whole job: its datasets, its shards, and what each node did."""

    datasets: list[DatasetReport]
    shards: int = 0
    converted: int = 0
    reused: int = 0
    read_bytes: int = 0
    part_bytes: int = 0
    nodes: dict[str, dict[str, float]] = field(default_factory=dict)
    """node -> {"shards": n, "seconds": busy seconds}."""
    shard_seconds: float = 0.0
    """Wall time of the shard jobs."""
    assemble_seconds: float = 0.0
    seconds: float = 0.0

    def summary(self) -> list[str]:
        made = [d for d in self.datasets if d.status == "converted"]
        existed = sum(d.status == "existed" for d in self.datasets)
        lines = [
            f"{len(made)} of {len(self.datasets)} datasets converted"
            + (f", {existed} already there" if existed else "")
            + f" in {format_duration(self.seconds)}: {self.shards} shards "
            f"({self.converted} converted, {self.reused} reused from an earlier run), "
            f"{format_size(self.read_bytes)} of shards read, {format_size(self.part_bytes)} "
            f"written; shards {format_duration(self.shard_seconds)}, assembly "
            f"{format_duration(self.assemble_seconds)}"
        ]
        wall = max(self.shard_seconds, 1e-9)
        for node, n in sorted(self.nodes.items()):
            lines.append(
                f"  node {node[:12]}: {int(n['shards'])} shards, {n['shards'] / wall:.3g} "
                f"shards/s, {n['seconds'] / max(n['shards'], 1):.3g} s per shard"
            )
        for d in self.datasets:
            what = f"{d.family} {d.dataset}".strip()
            if d.status == "pending":
                lines.append(f"  {d.task} ({what}): not assembled")
                continue
            lines.append(
                f"  {d.out}: {d.task} ({what}), {d.segments:,} segments, {d.steps:,} steps, "
                f"{d.episodes:,} episodes, {format_size(d.bytes)}"
                + (" (already there)" if d.status == "existed" else "")
                + (f", {d.skipped_records} damaged records skipped" if d.skipped_records else "")
            )
        return lines


# --- jobs that run on the workers ---------------------------------------------------------


@dataclass(frozen=True)
class _Shard:
    dataset: int
    index: int
    source: str  # a file, or with fetch an object
    part: str
    job: ShardJob
    fetch: Fetch | None


@dataclass(frozen=True)
class _Assembly:
    dataset: int
    out: str
    parts: tuple[str, ...]
    schema: Schema
    provenance: Mapping[str, Any]
    overwrite: bool


class _Sender:
    """Progress messages of one job, one every ``_SEND_EVERY`` units."""

    def __init__(self, kind: str):
        self.kind, self.held = kind, 0

    def __call__(self, n: int) -> None:
        self.held += n
        if self.held >= _SEND_EVERY:
            self.flush()

    def flush(self) -> None:
        if self.held:
            send((self.kind, self.held))
            self.held = 0


def _json(value: Any) -> Any:
    return json.loads(json.dumps(value))


def _part_key(job: ShardJob, source: Mapping[str, Any]) -> dict[str, Any]:
    """What a part is made from: a part recording another key is not this shard's."""
    from rlu import __version__

    return _json(
        {
            "rlu_version": __version__,
            "family": job.family,
            "schema": job.schema.to_json(),
            "meta": dict(job.meta),
            "verify": job.verify,
            "on_error": job.on_error,
            "source": dict(source),
        }
    )


def _reuse(part: Path, key: Mapping[str, Any]) -> tuple[dict[str, Any], int] | None:
    """The stats and size of a finished part made from ``key`` whose files match their sha256;
    None (and the part removed) when it is missing, of other inputs or damaged."""
    if not (part / MANIFEST).is_file():
        return None
    try:
        manifest = read_manifest(part)
        ok = manifest["provenance"].get("part") == key and not verify_checksums(part, manifest)
    except FormatError:
        ok = False
    if not ok:
        shutil.rmtree(part, ignore_errors=True)
        return None
    size = sum(int(f["bytes"]) for f in manifest["files"].values())
    return dict(manifest["provenance"]["shard"]), size


def run_shard(shard: _Shard) -> ShardResult:
    """One shard: fetched (or reused) and verified, then decoded into its part, or the part of an
    earlier run reused (see the module docstring). Runs on a worker."""
    t0 = time.monotonic()
    path, sha, obj = shard.source, None, None
    if shard.fetch is not None:
        obj = shard.source
        sender = _Sender("downloaded")
        got: Fetched = shard.fetch.downloader().fetch_one(obj, on_bytes=sender)
        sender.flush()
        path, sha = got.path, got.sha256
        source = {"name": os.path.basename(path), "bytes": got.size, "sha256": sha}
    else:
        st = os.stat(path)
        source = {"name": os.path.basename(path), "bytes": st.st_size, "mtime_ns": st.st_mtime_ns}
    key = _part_key(shard.job, source)
    part = Path(shard.part)
    found = _reuse(part, key)
    reused = found is not None
    if found is None:
        found = _write_part(shard.job, path, part, key)
    stats, size = found
    return ShardResult(
        shard.dataset,
        shard.index,
        stats,
        str(part),
        size,
        reused,
        node_name(),
        time.monotonic() - t0,
        sha,
        obj,
    )


def _write_part(
    job: ShardJob, path: str, part: Path, key: Mapping[str, Any]
) -> tuple[dict[str, Any], int]:
    part.parent.mkdir(parents=True, exist_ok=True)
    # a name of this attempt's own: an overlapping attempt of the same shard writes beside it
    tmp = part.with_name(f"{part.name}.{uuid.uuid4().hex[:12]}")
    stats: dict[str, Any] = {}
    steps = _Sender("steps")
    with DatasetWriter(tmp, job.schema, provenance={"part": key}) as writer:
        for batch, st in shard_batches(job, path, columns=True):
            if st is not None:
                stats = st
                continue
            assert batch is not None  # a pair holds a batch or the stats
            before = writer.num_steps
            write_batch(writer, batch)
            steps(writer.num_steps - before)
        writer.provenance["shard"] = stats
    steps.flush()
    size = sum(f.stat().st_size for f in tmp.rglob("*") if f.is_file() and f.name != MANIFEST)
    try:
        move_into_place(tmp, part)
    except OSError as e:
        if e.errno not in (errno.ENOTEMPTY, errno.EEXIST):
            raise
        shutil.rmtree(tmp)  # another attempt of this shard finished first: the same bytes
    return stats, size


def assemble(a: _Assembly) -> dict[str, Any]:
    """One dataset from its parts, in shard order; the parts' folder removed after. Runs on a
    worker."""
    sender = _Sender("assembled")
    with DatasetWriter(a.out, a.schema, provenance=a.provenance, overwrite=a.overwrite) as w:
        for part in a.parts:
            w.append_dataset(part, on_bytes=sender)
        counts = {"segments": w.num_segments, "steps": w.num_steps, "episodes": w.num_episodes}
    sender.flush()
    shutil.rmtree(parts_folder(a.out), ignore_errors=True)
    size = sum(f.stat().st_size for f in Path(a.out).rglob("*") if f.is_file())
    return {"dataset": a.dataset, **counts, "bytes": size}


def _fetch(fetch: Fetch, obj: str) -> Fetched:
    sender = _Sender("downloaded")
    got = fetch.downloader().fetch_one(obj, on_bytes=sender)
    sender.flush()
    return got


# --- the driver ----------------------------------------------------------------------------


def parts_folder(out: str | os.PathLike) -> Path:
    """Where the parts of the dataset at ``out`` wait for their assembly: ``.<name>.parts``."""
    out = Path(out)
    return out.parent / f".{out.name}.parts"


def check_shared_path(path: str | os.PathLike, flag: str) -> None:
    """Refuse an object-store URL where a shared filesystem path is needed."""
    text = os.fspath(path)
    if text.lower().startswith(_URL_SCHEMES):
        raise RluError(
            f"{flag} {text}: an object-store URL, not a path; rlu reads and writes a folder every "
            "node sees as a filesystem (NFS, Lustre, EFS, ...): mount the bucket's data there, "
            "or use a shared filesystem"
        )


def _run_assemblies(
    assemblies: list[_Assembly],
    results: dict[tuple[int, int], ShardResult],
    report: JobReport,
    backend: Backend,
    progress: bool,
    retries: int,
) -> None:
    """One assembly job per dataset whose shards are converted, each filling in its dataset's
    report; a bar counts the parts' bytes assembled."""
    total = sum(results[a.dataset, i].part_bytes for a in assemblies for i in range(len(a.parts)))
    bar = Progress(total, "assemble", "B", quiet=not progress)
    done = 0

    def assembled(i: int, got: dict[str, Any]) -> None:
        nonlocal done
        d = report.datasets[got["dataset"]]
        d.status, d.segments, d.steps = "converted", got["segments"], got["steps"]
        d.episodes, d.bytes = got["episodes"], got["bytes"]
        done += 1
        bar.set_postfix(datasets=f"{done}/{len(assemblies)}")

    def message(m: tuple[str, int]) -> None:
        if m[0] == "assembled":
            bar.update(m[1])

    with bar:
        run_jobs(
            assemble,
            [(a,) for a in assemblies],
            _backend_for(backend, len(assemblies)),
            on_result=assembled,
            on_message=message,
            retries=retries,
        )


def convert_release(
    datasets: Sequence[DatasetJob],
    backend: Backend,
    *,
    fetch: Fetch | None = None,
    verify: bool = True,
    on_error: str = "raise",
    image_encoding: str | None = None,
    overwrite: bool = False,
    progress: bool = False,
    retries: int = 3,
) -> JobReport:
    """Make every dataset of ``datasets`` on ``backend``: one job per shard, then one assembly
    job per dataset (see the module docstring). The first error stops the job (the parts
    finished so far stay, for the next run) and is raised. A Ray backend at a HOST:PORT that
    does not answer is refused in seconds, before a shard is read or a folder made
    (``rlu.workers.Backend.reach``)."""
    backend.reach()
    t0 = time.monotonic()
    report = JobReport([DatasetReport(d.out, d.task, d.family, d.dataset, len(d.shards))
                        for d in datasets])  # fmt: skip
    if fetch is not None:
        check_shared_path(fetch.cache_dir, "--cache-dir")
    outs = [os.path.abspath(d.out) for d in datasets]
    if len(set(outs)) != len(outs):
        raise RluError("two datasets of this job have the same output folder; give --out-root")
    plans, shards = [], []
    for k, d in enumerate(datasets):
        check_shared_path(d.out, "--out")
        root = release_dir(fetch.cache_dir) if fetch is not None else None
        paths = [_cache_path(root, o) for o in d.shards] if root else list(d.shards)
        plan = plan_conversion(
            paths,
            d.family,
            d.task,
            challenge=d.challenge,
            run=d.run,
            verify=verify,
            on_error=on_error,
            image_encoding=image_encoding,
            provenance=d.provenance,
            check_files=fetch is None,
        )
        plans.append(plan)
        check_output(d.out, paths, MANIFEST, "dataset")
        if (Path(d.out) / MANIFEST).is_file() and not overwrite:
            _existing(report.datasets[k])
            continue
        folder = parts_folder(d.out)
        for i, src in enumerate(d.shards):
            part = folder / f"{i:05d}"
            shards.append(_Shard(k, i, src, str(part), plan.job, fetch))
    results: dict[tuple[int, int], ShardResult] = {}
    if shards:
        _run_shards(shards, backend, report, results, progress, retries)
    report.shard_seconds = time.monotonic() - t0
    assemblies = []
    for k, d in enumerate(datasets):
        if report.datasets[k].status == "existed":
            continue
        got = [results[k, i] for i in range(len(d.shards))]
        prov = dict(plans[k].provenance)
        if fetch is not None:  # what load_dataset(source="release") records
            prov.update(
                dataset=d.dataset,
                objects=list(d.shards),
                sha256={r.object: r.sha256 for r in got},
            )
        record_shards(prov, [r.stats for r in got])
        report.datasets[k].reused = sum(r.reused for r in got)
        report.datasets[k].skipped_records = prov["skipped_records"]
        parts = tuple(r.part for r in got)
        assemblies.append(_Assembly(k, d.out, parts, plans[k].job.schema, prov, overwrite))
    t1 = time.monotonic()
    if assemblies:
        _run_assemblies(assemblies, results, report, backend, progress, retries)
    report.assemble_seconds = time.monotonic() - t1
    report.seconds = time.monotonic() - t0
    return report


def _cache_path(root: str, obj: str) -> str:
    return os.path.join(root, *obj.split("/"))


def _existing(d: DatasetReport) -> None:
    m = read_manifest(d.out)
    d.status = "existed"
    c = m["counts"]
    d.segments, d.steps, d.episodes = c["segments"], c["steps"], c["episodes"]
    d.bytes = sum(int(f["bytes"]) for f in m["files"].values())


def _backend_for(backend: Backend, jobs: int) -> Backend:
    """Local: no more processes than jobs."""
    if backend.kind == "local":
        return dataclasses.replace(backend, workers=max(1, min(backend.workers, jobs)))
    return backend


def _run_shards(
    shards: list[_Shard],
    backend: Backend,
    report: JobReport,
    results: dict[tuple[int, int], ShardResult],
    progress: bool,
    retries: int,
) -> None:
    bar = Progress(len(shards), "convert", "shards", quiet=not progress)
    live = {"downloaded": 0, "steps": 0}

    def show() -> None:
        fields: dict[str, Any] = {"read": format_size(report.read_bytes)}
        if live["downloaded"]:
            fields["downloaded"] = format_size(live["downloaded"])
        fields["steps"] = live["steps"]
        if report.reused:
            fields["reused"] = report.reused
        fields["nodes"] = len(report.nodes)
        bar.set_postfix(**fields)

    def finished(i: int, r: ShardResult) -> None:
        results[r.dataset, r.index] = r
        report.shards += 1
        report.reused += r.reused
        report.converted += not r.reused
        if not r.reused:
            report.read_bytes += int(r.stats["bytes"])
            report.part_bytes += r.part_bytes
        node = report.nodes.setdefault(r.node, {"shards": 0, "seconds": 0.0})
        node["shards"] += 1
        node["seconds"] += r.seconds
        bar.update(1)
        show()

    def message(m: tuple[str, int]) -> None:
        if m[0] in live:
            live[m[0]] += m[1]
            show()

    # each family's Family.job_memory: a node runs no more shard jobs than its memory holds
    memory = max(get_family(s.job.family).job_memory for s in shards)
    with bar:
        run_jobs(
            run_shard,
            [(s,) for s in shards],
            _backend_for(backend, len(shards)),
            on_result=finished,
            on_message=message,
            retries=retries,
            resources={"memory": memory},
            ray_check=lambda ray: check_ray_nodes(ray, memory),
        )


def check_ray_nodes(ray: Any, memory: int) -> None:
    """Refuse, before submitting anything, a cluster where no shard task could ever start (Ray
    would wait for a node forever): none alive with a CPU and ``memory`` bytes."""
    best = max(
        (
            n["Resources"].get("memory", 0.0)
            for n in ray.nodes()
            if n.get("Alive") and n["Resources"].get("CPU", 0.0) >= 1
        ),
        default=None,
    )
    if best is None:
        raise RluError("the Ray cluster has no node with a CPU, so no shard task could start; "
                       "add worker nodes (a head started with --num-cpus=0 runs none)")  # fmt: skip
    if best < memory:
        raise RluError(
            f"every Ray node offers less memory than a shard task asks for "
            f"({format_size(best)} < {format_size(memory)}); use nodes with more memory"
        )


def fetch_release(
    objects: Sequence[str], backend: Backend, fetch: Fetch, progress: bool = False, retries: int = 3
) -> list[Fetched]:
    """Download (or reuse, verified) every object into the shared cache, one job per object on
    ``backend``; returns them in order. The first file that fails ends the job."""
    check_shared_path(fetch.cache_dir, "--cache-dir")
    objects = list(objects)
    got: list[Fetched | None] = [None] * len(objects)
    bar = Progress(None, "download", "B", quiet=not progress)
    counts = {"files": 0, "reused": 0}

    def finished(i: int, f: Fetched) -> None:
        got[i] = f
        counts["files"] += 1
        counts["reused"] += f.reused
        bar.set_postfix(files=f"{counts['files']}/{len(objects)}", reused=counts["reused"])

    def message(m: tuple[str, int]) -> None:
        if m[0] == "downloaded":
            bar.update(m[1])

    with bar:
        run_jobs(
            _fetch,
            [(fetch, o) for o in objects],
            _backend_for(backend, len(objects)),
            on_result=finished,
            on_message=message,
            retries=retries,
            ray_check=lambda ray: check_ray_nodes(ray, 0),
        )
    return [f for f in got if f is not None]
