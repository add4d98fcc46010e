"""Worker processes that end with the process that started them.

A pool's workers outlive a parent killed by a signal (``kill``, ``kill -9``, an out-of-memory
kill): a sweep's or a generation's workers would go on training and hold their run folders'
locks, so the next ``rlu sweep`` / ``rlu generate`` finds them "in use". Every worker rlu starts
calls :func:`die_with_parent` first.

Standard library only.
"""

from __future__ import annotations

import os
import signal
import threading
import time


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
