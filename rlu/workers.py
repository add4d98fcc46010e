"""The one runner of independent jobs (local process pool or Ray), and worker processes that
end with the process that started them.

A pool's workers outlive a parent killed by a signal (``kill``, ``kill -9``, an out-of-memory
kill): a sweep's or a generation's workers would go on training and hold their run folders'
locks, so the next ``rlu sweep`` / ``rlu generate`` finds them "in use". Every worker rlu starts
calls :func:`die_with_parent` first.

Standard library only.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any


def die_with_parent(parent: int) -> None:
    """End this process when process ``parent`` dies, ``kill -9`` included.

    Linux: ``prctl(PR_SET_PDEATHSIG, SIGKILL)``, then a check that the parent did not die before
    the call; elsewhere a thread that watches the parent's id.
    """
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(1, signal.SIGKILL) == 0:  # 1: PR_SET_PDEATHSIG
            if os.getppid() != parent:
                os._exit(1)
            return
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass

    def watch() -> None:  # pragma: no cover - not Linux
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="rlu-parent-watch", daemon=True).start()


# --- the runner -----------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Backend:
    """Where a fan-out of independent jobs runs (sweeps, generation runs, the quick start,
    conversion shards)."""

    kind: str = dataclasses.field(
        default="local", metadata={"choices": ("local", "ray"), "flag": "--backend"}
    )
    """local (this machine: in this process when workers is 1, else a pool of spawned
    processes) or ray (a Ray cluster)."""
    workers: int = dataclasses.field(default=1, metadata={"min": 1, "metavar": "N"})
    """Local: processes at once (the results do not depend on it)."""
    address: str | None = dataclasses.field(default=None, metadata={"flag": "--ray-address"})
    """Ray: the cluster's address (default: start a local instance, stopped at the end)."""
    gpus_per_job: float = dataclasses.field(
        default=0.0, metadata={"min": 0.0, "flag": "--gpus-per-run"}
    )
    """Ray: GPUs each job asks for; a fraction shares one (0.25: four per GPU)."""

    def __post_init__(self) -> None:
        from rlu.types import RluError

        if self.kind not in ("local", "ray"):
            raise RluError(f"backend {self.kind!r}; use 'local' or 'ray'")
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 1:
            raise RluError(f"--workers {self.workers!r}: give at least 1 process")
        from rlu.devices import check_gpus_per_run

        check_gpus_per_run(self.gpus_per_job)
        if self.kind == "local" and self.gpus_per_job:
            raise RluError(
                "--gpus-per-run asks Ray for GPUs; use --backend ray, or drop it (local runs all "
                "see the machine's GPUs)"
            )


_CHANNEL: Any = None  # a worker process's queue to the parent's on_message


def _init_worker(parent: int, channel: Any, sys_path: tuple[str, ...]) -> None:
    global _CHANNEL
    die_with_parent(parent)  # a killed parent leaves no job running on, holding its locks
    _CHANNEL = channel
    for p in sys_path:  # workers import the user's (or the tests') modules as the parent does
        if p not in sys.path:
            sys.path.append(p)


def send(message: Any) -> None:
    """From inside a job: pass ``message`` to the parent's ``on_message`` (progress). Dropped
    on Ray, which has no channel back."""
    if _CHANNEL is not None:
        _CHANNEL.put(message)
    elif _LOCAL_SINK is not None:
        _LOCAL_SINK(message)


_LOCAL_SINK: Callable[[Any], None] | None = None


def run_jobs(
    fn: Callable[..., Any],
    jobs: Sequence[tuple[Any, ...]],
    backend: Backend,
    on_result: Callable[[int, Any], None],
    on_error: Callable[[int, BaseException], None] | None = None,
    on_message: Callable[[Any], None] | None = None,
    ray_check: Callable[[Any], None] | None = None,
) -> None:
    """Run ``fn(*job)`` for every job on ``backend``; ``on_result(i, result)`` in this process
    as each finishes (in completion order). A job that raises: ``on_error(i, error)`` and the
    others go on, or, without ``on_error``, the error is raised once the pool is stopped. Every
    backend gives the same results (jobs must not depend on where they run). Workers die with
    this process, and Ctrl-C (any exception here) cancels every job not yet started."""
    global _LOCAL_SINK
    if backend.kind == "local" and (backend.workers <= 1 or len(jobs) <= 1):
        _LOCAL_SINK = on_message
        try:
            for i, job in enumerate(jobs):
                try:
                    result = fn(*job)
                except Exception as e:
                    if on_error is None:
                        raise
                    on_error(i, e)
                    continue
                on_result(i, result)
        finally:
            _LOCAL_SINK = None
        return
    if backend.kind == "local":
        _run_pool(fn, jobs, backend.workers, on_result, on_error, on_message)
    else:
        _run_ray(fn, jobs, backend, on_result, on_error, ray_check)


def _run_pool(fn, jobs, workers, on_result, on_error, on_message) -> None:
    import multiprocessing as mp
    import queue as queue_lib
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    # spawn: a fresh interpreter per worker (torch and fork do not mix: a fork of a process
    # whose OpenMP pool has run can hang)
    ctx = mp.get_context("spawn")
    channel = ctx.Queue() if on_message is not None else None
    paths = tuple(p for p in sys.path if p and os.path.isdir(p))
    pool = ProcessPoolExecutor(
        min(workers, len(jobs)), ctx, _init_worker, (os.getpid(), channel, paths)
    )

    def drain() -> None:
        while channel is not None:
            try:
                on_message(channel.get_nowait())
            except queue_lib.Empty:
                return

    try:
        futures = {pool.submit(fn, *job): i for i, job in enumerate(jobs)}
        pending = set(futures)
        while pending:
            done, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
            drain()
            for f in done:
                i = futures[f]
                try:
                    result = f.result()
                except Exception as e:
                    if on_error is None:
                        raise
                    on_error(i, e)
                    continue
                on_result(i, result)
        drain()
    except BaseException:  # Ctrl-C or a job's error: start no further job
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def _run_ray(fn, jobs, backend: Backend, on_result, on_error, ray_check) -> None:
    from rlu.types import RluError, install_hint

    try:
        import ray
    except ImportError:
        raise RluError(f"the Ray backend needs ray: {install_hint('distributed')}") from None
    from rlu.devices import ray_options

    started = False
    if not ray.is_initialized():
        if backend.address:
            ray.init(address=backend.address, log_to_driver=False)
        else:
            # "local": a new instance of our own, never a cluster found on this machine
            ray.init(address="local", num_cpus=max(1, os.cpu_count() or 1),
                     include_dashboard=False, log_to_driver=False)  # fmt: skip
        started = True
    try:
        if ray_check is not None:
            ray_check(ray)
        paths = tuple(p for p in sys.path if p and os.path.isdir(p))
        remote = ray.remote(**ray_options(backend.gpus_per_job))(_ray_job)
        pending = {remote.remote(paths, fn, *job): i for i, job in enumerate(jobs)}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    i = pending.pop(ref)
                    try:
                        result = ray.get(ref)
                    except Exception as e:
                        if on_error is None:
                            raise
                        on_error(i, _ray_cause(e))
                        continue
                    on_result(i, result)
        except BaseException:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
    finally:
        if started:
            ray.shutdown()


def _ray_job(sys_path: tuple[str, ...], fn: Callable[..., Any], *args: Any) -> Any:
    for p in sys_path:
        if p not in sys.path:
            sys.path.append(p)
    return fn(*args)


def _ray_cause(error: BaseException) -> BaseException:
    """The job's own exception inside Ray's wrapper (a RayTaskError is also an instance of it)."""
    return error
