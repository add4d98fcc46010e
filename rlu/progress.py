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

MODES = ("bar", "lines", "quiet")
_BAR = 20  # characters of the bar itself
ENV = "RLU_PROGRESS"


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

    def _line(self, final: bool = False) -> None:
        self._last = self._clock()
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
