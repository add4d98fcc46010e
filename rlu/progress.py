"""One progress display for every long command: a bar on a terminal, plain lines in a log, or none.

```python
from rlu.progress import Progress

with Progress(total=len(files), desc="convert", unit="shards") as bar:
    for f in files:
        ...
        bar.update(1)
        bar.set_postfix(steps=steps)
```

Three modes, chosen once when the display is made:

- ``"bar"``: one line drawn at once, then redrawn in place (``\\r``) at most every ``redraw``
  seconds: percent, a bar, ``n/total``, elapsed time, ETA and rate; the default when the stream
  is a terminal.
- ``"lines"``: a plain line at most every ``interval`` seconds (default 10), the first one
  ``interval`` seconds in; never a ``\\r``, so a CI log or a file redirect reads top to bottom.
  The default when the stream is not a terminal.
- ``"quiet"``: nothing (``quiet=True``, a command's ``--quiet``).

``Progress.close`` writes the final state (and ends the bar's line) when the display showed
something or the job did work. A job that fails (``close(failed=True)``, or an exception through
the ``with`` block) before its first plain line, or before any work under a bar, leaves no line
of its own: its error is the only line on the screen.

``$RLU_PROGRESS`` (``bar``, ``lines`` or ``quiet``) overrides the automatic choice, for a log
that is a terminal or a terminal that wants lines; an explicit ``mode`` or ``quiet=True`` wins
over it. Output goes to ``sys.stderr`` unless ``stream`` says otherwise, so a command's stdout
stays what it prints as its result.

A job in a worker process (a sweep's run, a quick-start agent) reports through a
:class:`Relay`: its counts go to the process that started it (``rlu.workers.send``, on every
backend), where one :class:`Tally` adds every job's up into one display (steps, rate, ETA of
the whole fan-out) and keeps it alive with a line every ``interval`` seconds in a log even while
no job moves (an evaluation, a worker starting).

The final line is written once: a display whose last plain line already showed the whole job
done writes no second one at close.

The ETA and rate count only what this display saw (``initial`` units done before it started,
e.g. by a resumed run, move the bar but not the rate). ``total`` may be unknown (``None``) or
grow (``Progress.set_total``, e.g. bytes as downloads announce their sizes). Updates are
thread-safe, so worker threads may share one display.

Why not tqdm: the core depends on numpy only, and tqdm's output when stderr is not a terminal is
its bar rewritten with ``\\r`` into the log, not plain lines; the three modes here are about 200
lines of standard library.
"""

from __future__ import annotations

import os
import shutil
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TextIO

__all__ = [
    "ENV",
    "MODES",
    "RELAY_TAG",
    "Progress",
    "Relay",
    "Tally",
    "choose_mode",
    "format_duration",
    "format_size",
]

MODES = ("bar", "lines", "quiet")
"""The display modes: a redrawn bar, plain lines, nothing."""
_BAR = 20  # characters of the bar itself
ENV = "RLU_PROGRESS"
"""The environment variable that overrides the automatic mode (``bar``, ``lines``, ``quiet``)."""
RELAY_TAG = "rlu.progress"
"""The first item of every message a :class:`Relay` sends (``(RELAY_TAG, key, done, total)``)."""


def choose_mode(stream: TextIO, mode: str | None = None, quiet: bool = False) -> str:
    """The mode a display on ``stream`` takes: ``quiet``, else ``mode``, else ``$RLU_PROGRESS``,
    else ``bar`` on a terminal and ``lines`` elsewhere."""
    if quiet:
        return "quiet"
    if mode is None:
        env = os.environ.get(ENV, "").strip().lower()
        mode = env if env in MODES else None
    if mode is None:
        try:
            mode = "bar" if stream.isatty() else "lines"
        except (AttributeError, ValueError):  # a closed or foreign stream
            mode = "lines"
    if mode not in MODES:
        raise ValueError(f"progress mode {mode!r}; use one of {', '.join(MODES)}")
    return mode


def format_size(n: float) -> str:
    """Bytes in SI units: ``999 B``, ``12.5 MB``, ``3.21 GB``."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if abs(n) >= scale:
            return f"{n / scale:,.{2 if unit == 'GB' else 1}f} {unit}"
    return f"{n:,.0f} B"


def format_duration(seconds: float) -> str:
    """``m:ss`` under an hour, ``h:mm:ss`` above."""
    s = max(0, int(seconds + 0.5))
    h, rest = divmod(s, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class Progress:
    """A progress display (see the module docstring); use as a context manager or call close.

    Args:
        total: units of the whole job, ``None`` when unknown.
        desc: what is running, the first word of every line (``download``, ``convert``).
        unit: what is counted (``files``, ``episodes``); ``"B"`` prints sizes (``12.5 MB``).
        quiet: show nothing.
        mode: ``"bar"``, ``"lines"`` or ``"quiet"``; default: see :func:`choose_mode`.
        stream: where the display goes (default ``sys.stderr``).
        interval: seconds between two plain lines in ``lines`` mode.
        redraw: seconds between two redraws of the bar.
        initial: units already done before this display started (a resumed job).
        clock: seconds, monotonic (tests pass a fake one).
    """

    def __init__(
        self,
        total: float | None = None,
        desc: str = "",
        unit: str = "it",
        *,
        quiet: bool = False,
        mode: str | None = None,
        stream: TextIO | None = None,
        interval: float = 10.0,
        redraw: float = 0.2,
        initial: float = 0,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.stream = stream if stream is not None else sys.stderr
        self.mode = choose_mode(self.stream, mode, quiet)
        self.total = total
        self.desc = desc
        self.unit = unit
        self.interval = interval
        self.redraw = redraw
        self.n = initial
        self._initial = initial
        self._clock = clock
        self._start = clock()
        # when the last line or bar was written: a bar is drawn at once, lines wait an interval
        self._last = self._start - (redraw if self.mode == "bar" else 0)
        self._postfix = ""
        self._lock = threading.RLock()
        self._closed = False
        self._width = 0  # characters of the bar now on the terminal's line
        self._shown = False  # a line or a bar was written
        self._printed: tuple[Any, ...] | None = None  # (n, total, postfix) of the last line

    # --- what callers do -------------------------------------------------------------------
    def update(self, n: float = 1) -> None:
        """``n`` more units done."""
        with self._lock:
            self.n += n
            self._tick()

    def update_to(self, n: float) -> None:
        """``n`` units done in all (a counter the caller keeps)."""
        with self._lock:
            self.n = n
            self._tick()

    def set_total(self, total: float | None) -> None:
        """The whole job is ``total`` units after all (an estimate that got better)."""
        with self._lock:
            self.total = total
            self._tick()

    def set_postfix(self, **fields: Any) -> None:
        """Facts shown after the counts, ``key=value`` in the order given; replaces the last."""
        with self._lock:
            self._postfix = " ".join(f"{k}={_value(v)}" for k, v in fields.items())
            self._tick()

    def _set(self, n: float, total: float | None, **fields: Any) -> None:
        """Counts, total and postfix at once, then one redraw (a Tally's)."""
        with self._lock:
            self.n, self.total = n, total
            self._postfix = " ".join(f"{k}={_value(v)}" for k, v in fields.items())
            self._tick()

    def refresh(self) -> None:
        """Redraw the bar, or write a plain line if one is due, though nothing moved (the
        elapsed time goes on): a display that must show it is alive while its job waits."""
        with self._lock:
            self._tick()

    def note(self, text: str) -> None:
        """One line of text among the progress (the bar is redrawn below it); not in quiet."""
        with self._lock:
            if self.mode == "quiet" or self._closed:
                return
            if self.mode == "bar":
                self._clear()
                self._write(text + "\n")
                self._bar()
            else:
                self._write(text + "\n")

    def close(self, failed: bool = False) -> None:
        """The last state, then a newline after a bar; more calls do nothing.

        ``failed``: the job ended in an error, which its caller prints: plain lines that showed
        nothing yet stay silent, and a bar of a job that did nothing is wiped, so that the error
        is the only line.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            worked = self.n > self._initial
            if self.mode == "bar":
                if failed and not worked:
                    self._clear()  # nothing done: the error's line is the only one
                elif self._shown or worked:
                    self._bar()
                    self._write("\n")
            elif self.mode == "lines" and (self._shown or (worked and not failed)):
                done = self.total is not None and self.n >= self.total
                if not (done and self._printed == self._state()):  # that line is on screen
                    self._line(final=True)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close(failed=exc_type is not None)

    # --- what is shown ---------------------------------------------------------------------
    def render(self, final: bool = False, bar: str = "") -> str:
        """The text of one line of the display; ``bar`` goes after the percentage."""
        now = self._clock()
        elapsed = now - self._start
        done = self.n - self._initial
        rate = done / elapsed if elapsed > 0 else 0.0
        parts = [f"{self.desc}:" if self.desc else ""]
        if self.total:
            parts.append(f"{min(100.0, 100.0 * self.n / self.total):3.0f}%")
            parts.append(bar)
            parts.append(f"{self._count(self.n)}/{self._count(self.total)}{self._unit()}")
        else:
            parts.append(f"{self._count(self.n)}{self._unit()}")
        timing = format_duration(elapsed)
        if not final and self.total and rate > 0 and self.n < self.total:
            timing += f" ETA {format_duration((self.total - self.n) / rate)}"
        if done > 0 and elapsed > 0:
            timing += f", {self._rate(rate)}"
        parts.append(f"[{timing}]")
        if self._postfix:
            parts.append(self._postfix)
        return " ".join(p for p in parts if p)

    def _count(self, n: float) -> str:
        if self.unit == "B":
            return format_size(n)
        return f"{n:,.0f}" if float(n).is_integer() else f"{n:,.1f}"

    def _unit(self) -> str:
        return "" if self.unit == "B" or not self.unit else f" {self.unit}"

    def _rate(self, rate: float) -> str:
        if self.unit == "B":
            return f"{format_size(rate)}/s"
        if rate >= 1:
            return f"{rate:,.1f} {self.unit}/s"
        return f"{1 / rate:,.1f} s/{_singular(self.unit)}"

    # --- drawing ---------------------------------------------------------------------------
    def _tick(self) -> None:
        if self._closed or self.mode == "quiet":
            return
        now = self._clock()
        if self.mode == "bar" and now - self._last >= self.redraw:
            self._bar()
        elif self.mode == "lines" and now - self._last >= self.interval:
            self._line()

    def _state(self) -> tuple[Any, ...]:
        return (self.n, self.total, self._postfix)

    def _line(self, final: bool = False) -> None:
        self._last = self._clock()
        self._printed = self._state()
        self._write(self.render(final) + "\n")

    def _bar(self) -> None:
        self._last = self._clock()
        bar = ""
        if self.total:
            fill = int(_BAR * min(1.0, max(0.0, self.n / self.total)))
            bar = "|" + "#" * fill + " " * (_BAR - fill) + "|"
        cols = shutil.get_terminal_size((100, 24)).columns - 1
        text = self.render(bar=bar)
        if len(text) > cols:  # a narrow terminal: the numbers matter more than the bar
            text = self.render()[:cols]
        pad = " " * max(0, self._width - len(text))  # wipe what a longer bar left
        self._width = len(text)
        self._write("\r" + text + pad)

    def _clear(self) -> None:
        if self._width:
            self._write("\r" + " " * self._width + "\r")
            self._width = 0

    def _write(self, text: str) -> None:
        self._shown = True
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # stderr closed or gone: progress is not worth an error
            self.mode = "quiet"


def _singular(unit: str) -> str:
    return unit[:-1] if len(unit) > 2 and unit.endswith("s") else unit


def _value(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:,.4g}"
    if isinstance(v, int) and not isinstance(v, bool):
        return f"{v:,}"
    return str(v)


# --- jobs in other processes ------------------------------------------------------------------
class Relay:
    """The progress of one job running in a worker (``rlu.workers.run_jobs``), sent to the
    :class:`Tally` of the process that started it; it takes what a :class:`Progress` takes from
    the job (``update``, ``set_postfix``, ``note``, ``close``, a ``with`` block).

    ``rlu.training.train.train(..., progress=Relay(key))`` is how a sweep's runs report: the counts
    of this session's work (``start(total, initial)``: units done before it, a resumed run's, are
    left out) go out at most every ``interval`` seconds and at the end, as ``(RELAY_TAG, key,
    done, total)`` through ``rlu.workers.send`` (nothing when the parent listens to none).
    """

    def __init__(
        self, key: str, interval: float = 1.0, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.key = key
        self.interval = interval
        self._clock = clock
        self.n: float = 0
        self.total: float | None = None
        self._initial: float = 0
        self._last = -float("inf")

    def start(self, total: float | None, initial: float = 0) -> Relay:
        """The job is ``total`` units, ``initial`` of them done before; returns the relay."""
        self.total, self.n, self._initial = total, initial, initial
        self._send()
        return self

    def update(self, n: float = 1) -> None:
        """``n`` more units done."""
        self.n += n
        if self._clock() - self._last >= self.interval:
            self._send()

    def set_postfix(self, **fields: Any) -> None:
        """Facts of one job (an evaluation's return) stay in the job's own logs: not sent."""

    def note(self, text: str) -> None:
        """A line for the parent's display, above its bar."""
        from rlu.workers import send

        send((RELAY_TAG, self.key, "note", text))

    def close(self, failed: bool = False) -> None:
        """Send the last counts."""
        self._send()

    def __enter__(self) -> Relay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _send(self) -> None:
        from rlu.workers import send

        self._last = self._clock()
        total = None if self.total is None else self.total - self._initial
        send((RELAY_TAG, self.key, self.n - self._initial, total))


class Tally:
    """One display of many jobs, each reporting through a :class:`Relay`: the sum of their
    counts against the sum of their totals (a job not yet started counts as ``estimate``, or as
    the mean of the totals known), ``runs=done/jobs`` after it, and every ``interval`` seconds
    a plain line in a log (a bar redrawn on a terminal) while no job moves.

    Pass :meth:`message` as ``rlu.workers.run_jobs``' ``on_message``; call :meth:`finish` as
    each job ends (its count goes to its total) or :meth:`drop` when it failed.
    ``Progress``'s keywords (``stream``, ``mode``, ``interval``, ``clock``) pass through.
    """

    def __init__(
        self,
        jobs: int,
        desc: str = "",
        unit: str = "steps",
        estimate: float | None = None,
        *,
        quiet: bool = False,
        heartbeat: bool = True,
        **display: Any,
    ) -> None:
        self.jobs = jobs
        self.estimate = estimate
        self.bar = Progress(self._expected({}, 0), desc, unit, quiet=quiet, **display)
        self._done: dict[str, float] = {}
        self._totals: dict[str, float] = {}
        self._finished = 0
        self._dropped = 0
        self._extra: dict[str, Any] = {}
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.bar._set(0, self.bar.total, runs=f"0/{jobs}")
        if heartbeat and self.bar.mode != "quiet":
            self._thread = threading.Thread(target=self._beat, name="rlu-progress", daemon=True)
            self._thread.start()

    def message(self, m: Any) -> bool:
        """Take one message of a job; False (and nothing done) when it is no Relay's."""
        if not (isinstance(m, tuple) and len(m) == 4 and m[0] == RELAY_TAG):
            return False
        _, key, done, total = m
        with self._lock:
            if done == "note":
                self.bar.note(str(total))
                return True
            if key in self._totals and key not in self._done:
                return True  # finished already: a late message changes nothing
            self._done[key] = float(done)
            if total is not None:
                self._totals[key] = float(total)
            self._show()
        return True

    def finish(self, key: str) -> None:
        """Job ``key`` ended: all of its units count as done."""
        with self._lock:
            total = self._totals.get(key, self._done.get(key, 0.0))
            self._totals[key] = max(total, self._done.pop(key, 0.0))
            self._finished += 1
            self._show()

    def drop(self, key: str) -> None:
        """Job ``key`` failed: what it did still counts, what it had left does not."""
        with self._lock:
            self._totals[key] = self._done.pop(key, 0.0)
            self._finished += 1
            self._dropped += 1
            self._show()

    def note(self, text: str) -> None:
        """One line among the progress (see :meth:`Progress.note`)."""
        self.bar.note(text)

    def set_postfix(self, **fields: Any) -> None:
        """Facts shown after ``runs=...`` (e.g. ``failed=1``)."""
        with self._lock:
            self._extra = dict(fields)
            self._show()

    def close(self, failed: bool = False) -> None:
        """Stop the heartbeat and close the display (see :meth:`Progress.close`)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.bar.close(failed)

    def __enter__(self) -> Tally:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close(failed=exc_type is not None)

    def _expected(self, totals: dict[str, float], started: int) -> float | None:
        known = sum(totals.values())
        waiting = self.jobs - started
        if waiting <= 0:
            return known
        each = self.estimate
        if each is None and totals:
            each = known / len(totals)
        return None if each is None else known + waiting * each

    def _show(self) -> None:
        started = set(self._totals) | set(self._done)
        done = sum(self._done.values()) + sum(
            v for k, v in self._totals.items() if k not in self._done
        )
        total = self._expected(self._totals, len(started))
        self.bar._set(done, total, runs=f"{self._finished}/{self.jobs}", **self._extra)

    def _beat(self) -> None:
        step = min(1.0, max(0.05, self.bar.interval / 10))
        while not self._stop.wait(step):
            self.bar.refresh()
