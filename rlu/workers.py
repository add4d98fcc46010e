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
import ipaddress
import os
import re
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from rlu.files import Checked, bounds

__all__ = [
    "RAY_ADDRESS_FORMS",
    "RAY_CONNECT_TIMEOUT",
    "Backend",
    "check_ray_address",
    "die_with_parent",
    "node_name",
    "reach_ray_address",
    "run_jobs",
    "send",
]


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


# --- Ray addresses --------------------------------------------------------------------------
RAY_ADDRESS_FORMS = (
    "auto (the cluster this machine belongs to), local (a new instance of our own), HOST:PORT "
    "(a cluster's head node, e.g. 10.0.0.5:6379 or [::1]:6379) or ray://HOST:PORT (Ray Client)"
)
"""The ``--ray-address`` values rlu takes (what ``ray.init(address=...)`` takes, less the
forms it guesses at)."""
RAY_CONNECT_TIMEOUT = 5.0
"""Seconds rlu waits for a TCP connection to a HOST:PORT Ray address before ``ray.init`` (which
itself retries an unreachable head for a minute or more)."""
_LABEL = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)")


def _host_ok(host: str) -> bool:
    """An IPv4 literal, a bracketed IPv6 literal, or a hostname of letters, digits and hyphens
    (RFC 1123 labels of 1 to 63 characters, 253 in all)."""
    if host.startswith("[") and host.endswith("]"):
        try:
            return ipaddress.ip_address(host[1:-1]).version == 6
        except ValueError:
            return False
    if not host or len(host) > 253:
        return False
    if re.fullmatch(r"[0-9.]+", host):  # all digits and dots: an IPv4 literal or nothing
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            return False
        return True
    return all(_LABEL.fullmatch(label) for label in host.removesuffix(".").split("."))


def check_ray_address(address: str) -> tuple[str, int] | None:
    """Refuse a ``--ray-address`` that is none of ``RAY_ADDRESS_FORMS`` (an
    :class:`~rlu.types.RluError` naming the flag, the value and the forms); the (host, port) to
    connect to for HOST:PORT and ray://HOST:PORT, None for auto and local. Nothing is reached."""
    from rlu.types import RluError

    def refuse(why: str) -> RluError:
        return RluError(f"--ray-address {str(address)[:200]!r}: {why}; give {RAY_ADDRESS_FORMS}")

    if not isinstance(address, str):
        raise refuse("not a string")
    if address in ("auto", "local"):
        return None
    rest = address.removeprefix("ray://")
    host, colon, port = rest.rpartition(":")
    if not colon:
        raise refuse("no port (HOST:PORT)")
    if not re.fullmatch(r"[0-9]{1,5}", port) or not 1 <= int(port) <= 65535:
        raise refuse(f"port {port[:20]!r} is not a number from 1 to 65535")
    if ":" in host and not host.startswith("["):
        raise refuse("an IPv6 host goes in brackets ([::1]:6379)")
    if not _host_ok(host):
        raise refuse(f"host {host[:100]!r} is not an IP address or a hostname")
    return host.removeprefix("[").removesuffix("]"), int(port)


def reach_ray_address(address: str, timeout: float = RAY_CONNECT_TIMEOUT) -> None:
    """Check ``address`` (:func:`check_ray_address`) and, for HOST:PORT and ray://HOST:PORT, open
    (and close) a TCP connection to it within ``timeout`` seconds: a name that does not resolve,
    a refused connection, an unreachable network or no answer is one
    :class:`~rlu.types.RluError` naming the address and the fix, where ``ray.init`` would hang
    retrying. auto and local are left to Ray."""
    from rlu.types import RluError

    target = check_ray_address(address)
    if target is None:
        return
    host, port = target
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return
    except socket.gaierror as e:
        what = f"the host {host!r} does not resolve ({e.strerror or e})"
    except ConnectionRefusedError:
        what = f"{host} refused the connection (nothing listens on port {port})"
    except TimeoutError:
        what = f"no answer from {host}:{port} within {timeout:g} s"
    except OSError as e:
        what = f"{host}:{port} cannot be reached ({e.strerror or e})"
    raise RluError(
        f"--ray-address {address}: {what}; start the cluster's head there (`ray start --head "
        f"--port={port}` on that machine, `ray start --address={host}:{port}` on the others) "
        "and check the address, or drop --ray-address to run on a local Ray instance"
    )


# --- the runner -----------------------------------------------------------------------------
MAX_WORKERS = 1 << 16
"""Jobs running at once, at most."""
MAX_GPUS_PER_JOB = 1024.0
"""GPUs one job may ask Ray for, at most."""


@dataclasses.dataclass(frozen=True)
class Backend(Checked):
    """Where a fan-out of independent jobs runs (sweeps, generation runs, the quick start,
    conversion shards); every field is checked when it is made (``rlu.files.Checked``)."""

    kind: str = dataclasses.field(
        default="local", metadata=bounds(choices=("local", "ray"), flag="--backend")
    )
    """local (this machine: in this process when workers is 1, else a pool of spawned
    processes) or ray (a Ray cluster)."""
    workers: int = dataclasses.field(
        default=1, metadata=bounds(min=1, max=MAX_WORKERS, metavar="N")
    )
    """Local: processes at once (the results do not depend on it)."""
    address: str | None = dataclasses.field(default=None, metadata={"flag": "--ray-address"})
    """Ray: the cluster's address: auto, local, HOST:PORT or ray://HOST:PORT (default: start a
    local instance, stopped at the end)."""
    gpus_per_job: float = dataclasses.field(
        default=0.0, metadata=bounds(min=0.0, max=MAX_GPUS_PER_JOB, flag="--gpus-per-run")
    )
    """Ray: GPUs each job asks for; a fraction shares one (0.25: four per GPU)."""

    def __post_init__(self) -> None:
        super().__post_init__()  # every field's type and bounds (kind, workers, gpus_per_job)
        from rlu.devices import check_gpus_per_run
        from rlu.types import RluError

        check_gpus_per_run(self.gpus_per_job)
        if self.address is not None:
            check_ray_address(self.address)
        if self.kind == "local" and self.gpus_per_job:
            raise RluError(
                "--gpus-per-run asks Ray for GPUs; use --backend ray, or drop it (local runs all "
                "see the machine's GPUs)"
            )

    def reach(self) -> None:
        """On Ray at a HOST:PORT address: refuse, within ``RAY_CONNECT_TIMEOUT`` seconds, a
        cluster that does not answer (:func:`reach_ray_address`); commands call it before they
        make an output folder. Nothing for the local backend, auto or local."""
        if self.kind == "ray" and self.address is not None:
            reach_ray_address(self.address)


_CHANNEL: Any = None  # a worker process's queue to the parent's on_message


def _init_worker(parent: int, channel: Any, sys_path: tuple[str, ...]) -> None:
    global _CHANNEL
    die_with_parent(parent)  # a killed parent leaves no job running on, holding its locks
    _CHANNEL = channel
    for p in sys_path:  # workers import the user's (or the tests') modules as the parent does
        if p not in sys.path:
            sys.path.append(p)


def send(message: Any) -> None:
    """From inside a job: pass ``message`` to the parent's ``on_message`` (progress), on every
    backend (on Ray through a queue actor on the driver's node; a message of a job whose node
    dies with it may be lost). Nothing happens when the parent gave no ``on_message``."""
    global _RAY_SENT
    if _CHANNEL is not None:
        _CHANNEL.put(message)
    elif _RAY_CHANNEL is not None:
        _RAY_CHANNEL.put.remote(message)
        _RAY_SENT = True
    elif _LOCAL_SINK is not None:
        _LOCAL_SINK(message)


_LOCAL_SINK: Callable[[Any], object] | None = None
_RAY_CHANNEL: Any = None  # inside a Ray job: the driver's queue actor
_RAY_NODE: str | None = None  # inside a Ray job: the id of the node it runs on
_RAY_SENT = False  # this Ray job sent a message


def node_name() -> str:
    """Where the calling job runs: the Ray node's id inside a Ray job (several nodes of a test
    cluster share one host name), else this machine's host name."""
    if _RAY_NODE is not None:
        return _RAY_NODE
    import socket

    return socket.gethostname()


def _deliver(
    i: int,
    get: Callable[[], Any],
    on_result: Callable[[int, Any], None],
    on_error: Callable[[int, BaseException], None] | None,
) -> None:
    """Job ``i``'s outcome to its callback: ``on_result(i, get())``, or ``on_error(i, e)`` when
    ``get`` raises (re-raised without ``on_error``)."""
    try:
        result = get()
    except Exception as e:
        if on_error is None:
            raise
        on_error(i, e)
        return
    on_result(i, result)


def run_jobs(
    fn: Callable[..., Any],
    jobs: Sequence[tuple[Any, ...]],
    backend: Backend,
    on_result: Callable[[int, Any], None],
    on_error: Callable[[int, BaseException], None] | None = None,
    on_message: Callable[[Any], object] | None = None,
    ray_check: Callable[[Any], None] | None = None,
    retries: int = 3,
    resources: Mapping[str, float] | None = None,
) -> None:
    """Run ``fn(*job)`` for every job on ``backend``; ``on_result(i, result)`` in this process
    as each finishes (in completion order). A job that raises: ``on_error(i, error)`` and the
    others go on, or, without ``on_error``, the error is raised once the pool is stopped. Every
    backend gives the same results (jobs must not depend on where they run). Workers die with
    this process, and Ctrl-C (any exception here) cancels every job not yet started.

    ``on_message``: called here with what jobs :func:`send` (progress). Ray only: ``retries``,
    how many times a job whose worker or node died is run again (Ray's ``max_retries``; a job's
    own exception is never retried), so a job that may run twice must be idempotent;
    ``resources``, what each job asks for beyond its CPU and ``gpus_per_job`` (``{"memory":
    bytes}`` keeps Ray from packing more jobs onto a node than its memory holds)."""
    global _LOCAL_SINK
    if backend.kind == "local" and (backend.workers <= 1 or len(jobs) <= 1):
        _LOCAL_SINK = on_message
        try:
            for i, job in enumerate(jobs):
                _deliver(i, lambda: fn(*job), on_result, on_error)  # noqa: B023 (called now)
        finally:
            _LOCAL_SINK = None
        return
    if backend.kind == "local":
        _run_pool(fn, jobs, backend.workers, on_result, on_error, on_message)
    else:
        _run_ray(fn, jobs, backend, on_result, on_error, on_message, ray_check, retries, resources)


def _run_pool(
    fn: Callable[..., Any],
    jobs: Sequence[tuple[Any, ...]],
    workers: int,
    on_result: Callable[[int, Any], None],
    on_error: Callable[[int, BaseException], None] | None,
    on_message: Callable[[Any], object] | None,
) -> None:
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    # spawn: a fresh interpreter per worker (torch and fork do not mix: a fork of a process
    # whose OpenMP pool has run can hang)
    ctx = mp.get_context("spawn")
    # a SimpleQueue's put writes to the pipe before it returns (a Queue's feeder thread may still
    # hold a job's last messages when its result arrives: they were lost, a flaky tally)
    channel = ctx.SimpleQueue() if on_message is not None else None
    paths = tuple(p for p in sys.path if p and os.path.isdir(p))
    pool = ProcessPoolExecutor(
        min(workers, len(jobs)), ctx, _init_worker, (os.getpid(), channel, paths)
    )

    def drain() -> None:
        while channel is not None and on_message is not None and not channel.empty():
            on_message(channel.get())

    try:
        futures = {pool.submit(fn, *job): i for i, job in enumerate(jobs)}
        pending = set(futures)
        while pending:
            done, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
            drain()
            for f in done:
                _deliver(futures[f], f.result, on_result, on_error)
        drain()
    except BaseException:  # Ctrl-C or a job's error: start no further job
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)
    drain()


def _run_ray(
    fn: Callable[..., Any],
    jobs: Sequence[tuple[Any, ...]],
    backend: Backend,
    on_result: Callable[[int, Any], None],
    on_error: Callable[[int, BaseException], None] | None,
    on_message: Callable[[Any], object] | None,
    ray_check: Callable[[Any], None] | None,
    retries: int,
    resources: Mapping[str, float] | None,
) -> None:
    from rlu.system import install_hint
    from rlu.types import RluError

    try:
        import ray
    except ImportError:
        raise RluError(f"the Ray backend needs ray: {install_hint('distributed')}") from None
    from rlu.devices import ray_options

    started = False
    if not ray.is_initialized():
        if backend.address not in (None, "local"):
            reach_ray_address(backend.address)  # a dead head: seconds, not ray.init's minutes
            ray.init(address=backend.address, log_to_driver=False)
        else:
            # "local": a new instance of our own, never a cluster found on this machine
            ray.init(address="local", num_cpus=max(1, os.cpu_count() or 1),
                     include_dashboard=False, log_to_driver=False)  # fmt: skip
        started = True
    channel = None
    try:
        if ray_check is not None:
            ray_check(ray)
        if on_message is not None:
            channel = _ray_channel(ray)
        paths = tuple(p for p in sys.path if p and os.path.isdir(p))
        options: dict[str, Any] = {**ray_options(backend.gpus_per_job), **(resources or {})}
        remote = ray.remote(max_retries=retries, **options)(_ray_job)
        pending = {remote.remote(paths, channel, fn, *job): i for i, job in enumerate(jobs)}

        def drain() -> None:
            nonlocal channel
            if channel is None or on_message is None:  # a channel only with on_message
                return
            try:
                messages = ray.get(channel.take.remote())
            except Exception:  # noqa: BLE001 (the queue's node died: progress is not worth it)
                channel = None
                return
            for m in messages:
                on_message(m)

        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1, timeout=0.25)
                drain()
                for ref in done:
                    i = pending.pop(ref)
                    try:
                        result = ray.get(ref)
                    except Exception as e:
                        if on_error is None:
                            raise _ray_cause(e) from None
                        on_error(i, _ray_cause(e))
                        continue
                    on_result(i, result)
            drain()
        except BaseException:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
    finally:
        if channel is not None:
            ray.kill(channel)
        if started:
            ray.shutdown()


class _Queue:
    """Messages of a fan-out's Ray jobs for the driver (a Ray actor; see ``send``)."""

    def __init__(self) -> None:
        self.items: list[Any] = []

    def put(self, item: Any) -> None:
        self.items.append(item)

    def take(self) -> list[Any]:
        items, self.items = self.items, []
        return items

    def ping(self) -> None:
        pass


def _ray_channel(ray: Any) -> Any:
    """A queue actor on the driver's own node (it needs no CPU), so that a worker node that dies
    takes no message of the others with it."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    here = ray.get_runtime_context().get_node_id()
    actor = ray.remote(num_cpus=0, max_restarts=0)(_Queue)
    return actor.options(
        scheduling_strategy=NodeAffinitySchedulingStrategy(here, soft=True)
    ).remote()


def _ray_job(sys_path: tuple[str, ...], channel: Any, fn: Callable[..., Any], *args: Any) -> Any:
    global _RAY_CHANNEL, _RAY_NODE, _RAY_SENT
    for p in sys_path:
        if p not in sys.path:
            sys.path.append(p)
    import ray

    _RAY_CHANNEL, _RAY_SENT = channel, False
    _RAY_NODE = ray.get_runtime_context().get_node_id()
    try:
        return fn(*args)
    finally:
        _RAY_CHANNEL = None
        if _RAY_SENT:
            # an actor runs one caller's calls in order: once this returns, every message of
            # this job is in the queue, before the driver sees the job's result
            try:
                ray.get(channel.ping.remote(), timeout=60)
            except Exception:  # noqa: BLE001 (the queue's node died: progress is not worth it)
                pass


def _ray_cause(error: BaseException) -> BaseException:
    """The job's own exception out of Ray's wrapper (whose text carries the remote traceback),
    so that an RluError reads as its one line; anything else Ray raised (a node lost past its
    retries) as it is."""
    from ray.exceptions import RayTaskError

    if isinstance(error, RayTaskError) and isinstance(error.cause, Exception):
        return error.cause
    return error
