"""One writer per output: an exclusive lock beside a dataset, a run folder or a cache entry.

The lock of ``<dir>/<name>`` is the file ``<dir>/.<name>.lock`` holding the owner's PID, locked
with ``flock``. The kernel drops an ``flock`` when its holder dies, so the lock of a killed
process (``kill -9``) is simply taken over by the next writer, whatever the file still says; a
live holder makes the next writer fail at once with "in use by PID N" instead of writing over its
partial output. A lock file planted as a symbolic or hard link is refused, never written through
(:func:`rlu.files.open_private`). Forked children (conversion's reader processes) close their copy
of the lock at fork, so a lock lives exactly as long as the process that took it. The folders
a lock had to create for its file are removed with it when they are still empty (a run that
failed before writing anything leaves no folder behind).

Standard library only (``fcntl``: POSIX).
"""

from __future__ import annotations

import fcntl
import os
import time
from pathlib import Path

from rlu.files import open_private
from rlu.types import RluError

_HELD: set[int] = set()  # descriptors of locks this process holds (closed in forked children)


def _close_in_child() -> None:
    for fd in list(_HELD):
        try:
            os.close(fd)  # the child's copy only: the parent keeps its lock
        except OSError:
            pass
    _HELD.clear()


os.register_at_fork(after_in_child=_close_in_child)


def _make_folders(folder: Path) -> list[Path]:
    """``folder`` and its missing parents created; the ones created, outermost first."""
    missing = []
    p = folder
    while not os.path.lexists(p) and p != p.parent:
        missing.append(p)
        p = p.parent
    folder.mkdir(parents=True, exist_ok=True)
    return missing[::-1]


class LockBusy(RluError):
    """Another live process is writing the same output."""


def lock_path(target: str | os.PathLike) -> Path:
    target = Path(target)
    return target.parent / f".{target.name}.lock"


class OutputLock:
    """``with OutputLock(dest, "dataset"):`` -- exclusive, never waits; see the module docstring."""

    def __init__(self, target: str | os.PathLike, what: str = "output"):
        self.target = Path(target)
        self.path = lock_path(self.target)
        self.what = what
        self.fd: int | None = None
        self.made: list[Path] = []  # folders acquire() created, outermost first

    def acquire(self, wait: float = 0.0) -> OutputLock:
        """Take the lock; a live holder makes it fail at once, or after ``wait`` seconds of
        asking again (a cluster's retried job whose first attempt, on a node that died, may
        still hold the lock until the kernel or the file server drops it)."""
        if self.fd is not None:
            return self
        self.made = _make_folders(self.path.parent)
        deadline = time.monotonic() + wait
        pause = 0.02
        while True:
            fd = self._open()
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                pid = _read_pid(fd)
                os.close(fd)
                if time.monotonic() < deadline:
                    time.sleep(min(pause, max(0.0, deadline - time.monotonic())))
                    pause = min(2 * pause, 1.0)
                    continue
                holder = f"PID {pid}" if pid else "another process"
                raise LockBusy(
                    f"{self.target}: this {self.what} is in use by {holder} (lock file "
                    f"{self.path}); wait for it to finish or stop it, then run again"
                ) from None
            # A holder that released after we opened the file has unlinked it: lock the new one.
            try:
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
            self.fd = fd
            _HELD.add(fd)
            return self

    def _open(self) -> int:
        """The lock file, created if missing; a planted symlink (or hard link) is refused, never
        followed: the lock's PID would be written into whatever it points at."""
        what = f"lock file of {self.target}"
        try:
            try:
                return open_private(self.path, os.O_RDWR | os.O_CREAT, what)
            except FileNotFoundError:  # another lock's release removed the empty folder
                self.path.parent.mkdir(parents=True, exist_ok=True)
                return open_private(self.path, os.O_RDWR | os.O_CREAT, what)
        except OSError as e:
            raise RluError(f"{self.path}: the lock file cannot be opened ({e.strerror})") from None

    def release(self) -> None:
        fd, self.fd = self.fd, None
        if fd is None:
            return
        try:
            if os.stat(self.path).st_ino == os.fstat(fd).st_ino:
                os.unlink(self.path)  # while still locked: nobody can be inside a new lock yet
        except FileNotFoundError:
            pass
        finally:
            _HELD.discard(fd)
            os.close(fd)
        made, self.made = self.made, []
        for folder in reversed(made):  # innermost first; one that holds anything is kept
            try:
                os.rmdir(folder)
            except OSError:
                break

    @property
    def held(self) -> bool:
        return self.fd is not None

    def __enter__(self) -> OutputLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __del__(self) -> None:
        try:
            self.release()
        except Exception:  # noqa: BLE001 (interpreter shutdown: the kernel drops the lock)
            pass


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        return int(text) if text.isdigit() else None
    except OSError:
        return None
