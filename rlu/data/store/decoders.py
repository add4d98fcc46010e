"""Frame-inflating processes: a compressed column's random reads decoded on every core.

:meth:`rlu.data.store.ZlibColumn.take` (the uniform samplers' frames) inflates about 1,300
frames of 7 KB for one batch of 256 stacked Atari transitions. The inflaters release the GIL on
each call, but one call lasts only ~8 us, and two threads handing the GIL back and forth for
every frame decode at 1.2x one thread on two cores, where two processes decode at 1.8x
(``bench/stream.py``, the uniform figures). So a batch's reads are split between the calling
thread and ``cores - 1`` helper processes, each with its own interpreter:

- a helper is a ``python -c`` running :func:`main`, started on first use (not
  ``multiprocessing``: nothing of the caller's ``__main__`` is imported again), given a socket
  and a shared anonymous memory file (``memfd``) at its start; it ends when its socket closes,
  so it never outlives the process that started it;
- a task is one file's reads (offsets the caller computed from the column's checked offsets),
  the file named by its path and identified by its device and inode: a helper that opens
  another file under that path (replaced since the caller opened it) refuses the task, and the
  caller inflates those frames itself;
- the helper inflates into the shared memory, the caller copies the frames into its batch. A
  frame that is not a valid stream is reported back with its index and the reason, as the
  caller's own inflating reports it.

The bytes are the inflater's whoever inflates them, so which process decoded a frame never
changes a batch. ``RLU_DECODERS=0`` (or one core) keeps every frame in the calling thread.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

__all__ = ["MEMORY", "OPEN_FILES", "Decoders", "Task", "decoders", "main"]

MEMORY = 64 << 20
"""Bytes of shared memory per helper (frames per task: MEMORY // frame bytes)."""

OPEN_FILES = 64
"""Files a helper keeps open (a mixture's datasets), the least recently opened closed first."""

Task = tuple[str, str, int, int, np.ndarray, np.ndarray, np.ndarray, int]
"""``(inflater, path, st_dev, st_ino, reads, starts, ends, nbytes)``: the caller's inflater
(``rlu.data.inflate.current()``), the file; ``reads`` is an ``(r, 2)`` array of
``[a, b)`` ranges of the frames, each read in one ``pread`` from ``starts[a]`` to
``ends[b - 1]``; frame j is inflated into row j of the shared memory."""


class Decoders:
    """``n`` helper processes and their shared memory (see the module's docstring)."""

    def __init__(self, n: int):
        self.lock = threading.Lock()  # one batch at a time; other threads inflate themselves
        self.frames = 0  # frames the helpers inflated (the callers count them)
        self.helpers: list[tuple[subprocess.Popen[bytes], Connection, np.ndarray]] = []
        for _ in range(n):
            self.helpers.append(_start())

    def alive(self) -> bool:
        """Whether every helper still runs."""
        return all(proc.poll() is None for proc, _, _ in self.helpers)

    def close(self) -> None:
        """End the helpers (each ends when its socket closes) and wait for them."""
        for proc, conn, _ in self.helpers:
            conn.close()
            proc.wait()
        self.helpers = []

    def send(self, tasks: list[Task]) -> None:
        """One task to each of the first ``len(tasks)`` helpers; :meth:`collect` their replies."""
        for (_, conn, _), task in zip(self.helpers, tasks, strict=False):
            conn.send(task)

    def collect(self, count: int) -> list[tuple[np.ndarray, Any]]:
        """The replies of the first ``count`` helpers, each with the shared rows its task filled:
        None, ``("bad", j, why)`` for its first frame that is not a valid stream, ``("cut", lo,
        hi, got)`` for a read that found the file shorter, or ``("changed",)`` where the file
        under the path is not the caller's."""
        out = []
        for proc, conn, memory in self.helpers[:count]:
            try:
                reply = conn.recv()
            except (EOFError, OSError) as e:  # a helper killed from outside
                from rlu.types import RluError

                raise RluError(
                    f"a frame-inflating helper process (pid {proc.pid}) ended: {e or 'killed'}; "
                    "run again (RLU_DECODERS=0 inflates in the calling thread only)"
                ) from e
            out.append((memory, reply))
        return out


_DECODERS: tuple[int, Decoders | None] | None = None


def decoders() -> Decoders | None:
    """The process's helpers (``available_cores() - 1`` of them, started on first use, anew after
    a fork or after one of them ended), or None on one core or with ``RLU_DECODERS=0``."""
    global _DECODERS
    if (
        _DECODERS is None
        or _DECODERS[0] != os.getpid()
        or (_DECODERS[1] is not None and not _DECODERS[1].alive())
    ):
        from rlu.system import available_cores

        if _DECODERS is not None and _DECODERS[0] == os.getpid() and _DECODERS[1] is not None:
            _DECODERS[1].close()  # one of them ended: the others too, then all anew
        n = available_cores() - 1
        if os.environ.get("RLU_DECODERS", "") == "0" or sys.platform != "linux":
            n = 0
        _DECODERS = (os.getpid(), Decoders(n) if n > 0 else None)
    return _DECODERS[1]


def _start() -> tuple[subprocess.Popen[bytes], Connection, np.ndarray]:
    import mmap
    import socket

    mine, theirs = socket.socketpair()
    mem = os.memfd_create("rlu-frames", os.MFD_CLOEXEC)
    os.ftruncate(mem, MEMORY)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "from rlu.data.store.decoders import main; main()",
            str(theirs.fileno()),
            str(mem),
        ],  # fmt: skip
        pass_fds=(theirs.fileno(), mem),
        stdin=subprocess.DEVNULL,
        env={**os.environ, "RLU_DECODERS": "0"},
    )
    theirs.close()
    memory = np.frombuffer(mmap.mmap(mem, MEMORY), np.uint8)
    os.close(mem)
    return proc, Connection(mine.detach()), memory


def _serve(conn: Connection, memory: np.ndarray) -> None:
    from rlu.data import inflate

    files: dict[str, tuple[int, int, int]] = {}
    while True:
        try:
            inflater, path, dev, ino, reads, starts, ends, nbytes = conn.recv()
        except EOFError:
            return
        try:
            fd = _open(files, path, dev, ino)
            if fd is None:
                conn.send(("changed",))
                continue
            rows = memory[: len(starts) * nbytes].reshape(len(starts), nbytes)
            with inflate.use(inflater):
                reply = _inflate(fd, reads, starts, ends, rows, nbytes)
        except Exception as e:  # anything else (an unreadable file...): said to the caller
            reply = ("fail", f"{type(e).__name__}: {e}")
        conn.send(reply)


def _inflate(fd: int, reads: np.ndarray, starts: np.ndarray, ends: np.ndarray, rows: np.ndarray,
             nbytes: int) -> tuple[Any, ...] | None:  # fmt: skip
    from rlu.data.inflate import inflate_frames

    for a, b in reads.tolist():
        lo, hi = int(starts[a]), int(ends[b - 1])
        data = os.pread(fd, hi - lo, lo)
        if len(data) != hi - lo:
            return ("cut", lo, hi, len(data))
        bad = inflate_frames(data, starts[a:b] - lo, ends[a:b] - lo, rows[a:b], nbytes)
        if bad is not None:
            return ("bad", a + bad[0], bad[1])
    return None


def _open(files: dict[str, tuple[int, int, int]], path: str, dev: int, ino: int) -> int | None:
    held = files.get(path)
    if held is not None and held[1:] == (dev, ino):
        return held[0]
    if held is not None or len(files) >= OPEN_FILES:  # replaced, or the oldest file closed
        os.close(files.pop(path if held is not None else next(iter(files)))[0])
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return None
    st = os.fstat(fd)
    if (st.st_dev, st.st_ino) != (dev, ino):
        os.close(fd)
        return None
    files[path] = (fd, dev, ino)
    return fd


def main() -> None:
    """A helper's life: ``sys.argv[1:]`` are its socket's and its shared memory's descriptors."""
    import mmap

    conn = Connection(int(sys.argv[1]))
    _serve(conn, np.frombuffer(mmap.mmap(int(sys.argv[2]), MEMORY), np.uint8))
