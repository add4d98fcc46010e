"""rlu.progress: plain lines into a log, a redrawn bar on a terminal, nothing when quiet; a fake
clock makes every line exact."""

from __future__ import annotations

import io
import threading

import pytest

from rlu.progress import Progress, choose_mode, format_duration, format_size


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_lines_when_not_a_terminal(monkeypatch):
    monkeypatch.delenv("RLU_PROGRESS", raising=False)
    log, clock = io.StringIO(), Clock()
    with Progress(10, "convert", "shards", stream=log, interval=10, clock=clock) as bar:
        assert bar.mode == "lines"
        for _ in range(10):
            clock.t += 3
            bar.update()
            bar.set_postfix(steps=1234)
    assert "\r" not in log.getvalue()
    assert log.getvalue().splitlines() == [
        # one line every 10 s (after 12 s and 24 s), then the last one at close
        "convert:  40% 4/10 shards [0:12 ETA 0:18, 3.0 s/shard] steps=1,234",
        "convert:  80% 8/10 shards [0:24 ETA 0:06, 3.0 s/shard] steps=1,234",
        "convert: 100% 10/10 shards [0:30, 3.0 s/shard] steps=1,234",
    ]


def test_lines_of_bytes_with_a_growing_total():
    log, clock = io.StringIO(), Clock()
    bar = Progress(None, "download", "B", stream=log, clock=clock, mode="lines", interval=5)
    clock.t += 5
    bar.update(2_500_000)
    bar.set_total(10_000_000)
    clock.t += 5
    bar.update(2_500_000)
    bar.close()
    bar.close()  # a second close writes nothing
    assert log.getvalue().splitlines() == [
        "download: 2.5 MB [0:05, 500.0 kB/s]",
        "download:  50% 5.0 MB/10.0 MB [0:10 ETA 0:10, 500.0 kB/s]",
        "download:  50% 5.0 MB/10.0 MB [0:10, 500.0 kB/s]",
    ]


def test_a_job_that_fails_before_any_work_leaves_no_line():
    log = io.StringIO()
    with pytest.raises(RuntimeError):
        with Progress(3, "download", stream=log, mode="lines"):
            raise RuntimeError("refused")
    assert log.getvalue() == ""
    term = Terminal()
    Progress(3, "download", stream=term).close()
    assert term.getvalue() == ""
    term = Terminal()
    with pytest.raises(RuntimeError):
        with Progress(3, "download", stream=term) as bar:
            bar.set_postfix(files="0/3")  # drawn at once
            raise RuntimeError("refused")
    assert term.getvalue().startswith("\rdownload:   0%") and "\n" not in term.getvalue()
    assert term.getvalue().endswith(" \r")  # wiped: the error will be the only line


def test_the_rate_counts_only_this_run():
    log, clock = io.StringIO(), Clock()
    bar = Progress(100, "generate", "episodes", stream=log, clock=clock, initial=60, mode="lines")
    clock.t += 10
    bar.update(10)  # resumed at 60: 10 episodes in 10 s, 30 to go
    assert log.getvalue() == "generate:  70% 70/100 episodes [0:10 ETA 0:30, 1.0 episodes/s]\n"


def test_bar_on_a_terminal_is_redrawn_and_notes_go_above_it(monkeypatch):
    monkeypatch.delenv("RLU_PROGRESS", raising=False)
    term, clock = Terminal(), Clock()
    bar = Progress(4, "train", "steps", stream=term, clock=clock)
    assert bar.mode == "bar"
    clock.t += 1
    bar.update(1)  # the first: drawn at once
    bar.update(1)  # within the redraw interval: not drawn
    clock.t += 1
    bar.note("eval: return 812.5")
    bar.update(2)
    bar.close()
    out = term.getvalue()
    assert out.endswith("\n") and out.count("\n") == 2  # the note's and the close's
    first, rest = out.split("eval: return 812.5\n")
    assert first.startswith("\rtrain:  25% |#####               | 1/4 steps [0:01 ETA 0:03")
    assert first.endswith("\r")  # the bar was wiped before the note
    assert rest.split("\r")[-1].startswith("train: 100% |####################| 4/4 steps [0:02,")


def test_quiet_and_the_environment(monkeypatch):
    out = io.StringIO()
    bar = Progress(2, "x", stream=out, quiet=True, mode="bar")
    bar.update(2)
    bar.note("hidden")
    bar.close()
    assert out.getvalue() == "" and bar.mode == "quiet"
    monkeypatch.setenv("RLU_PROGRESS", "lines")
    assert choose_mode(Terminal()) == "lines"
    assert choose_mode(Terminal(), mode="bar") == "bar"
    assert choose_mode(Terminal(), quiet=True) == "quiet"
    monkeypatch.setenv("RLU_PROGRESS", "quiet")
    assert choose_mode(io.StringIO()) == "quiet"
    with pytest.raises(ValueError, match="progress mode"):
        choose_mode(io.StringIO(), mode="fancy")


def test_threads_share_one_display():
    log, clock = io.StringIO(), Clock()
    bar = Progress(8000, "download", "B", stream=log, clock=clock, mode="lines")

    def work() -> None:
        for _ in range(1000):
            bar.update(1)

    threads = [threading.Thread(target=work) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert bar.n == 8000


def test_a_closed_stream_silences_the_display():
    log = io.StringIO()
    bar = Progress(2, "x", stream=log, mode="lines", interval=0)
    log.close()
    bar.update(1)  # no error: progress is never worth one
    bar.close()
    assert bar.mode == "quiet"


def test_formats():
    assert format_size(999) == "999 B"
    assert format_size(12_500_000) == "12.5 MB"
    assert format_size(3_210_000_000) == "3.21 GB"
    assert format_duration(59.6) == "1:00"
    assert format_duration(3725) == "1:02:05"


def test_the_final_line_is_written_once():
    """A last plain line that already showed the whole job done is not written again at close
    (the quick start's last line used to be printed twice)."""
    log, clock = io.StringIO(), Clock()
    with Progress(2, "sweep", "runs", stream=log, clock=clock, mode="lines", interval=10) as bar:
        clock.t += 5
        bar.update(1)
        clock.t += 6
        bar.update(1)  # 100%, and 11 s since the start: a line now
    assert log.getvalue().splitlines() == ["sweep: 100% 2/2 runs [0:11, 5.5 s/run]"]
    log = io.StringIO()
    with Progress(2, "x", "runs", stream=log, clock=clock, mode="lines", interval=10) as bar:
        clock.t += 11
        bar.update(1)
        bar.update(1)  # done within the interval of the last line: close writes the final one
    assert [line.split(" [")[0] for line in log.getvalue().splitlines()] == [
        "x:  50% 1/2 runs",
        "x: 100% 2/2 runs",
    ]


def test_refresh_writes_a_due_line_though_nothing_moved():
    log, clock = io.StringIO(), Clock()
    bar = Progress(100, "sweep", "steps", stream=log, clock=clock, mode="lines", interval=10)
    clock.t += 4
    bar.update(10)
    bar.refresh()  # not due
    clock.t += 8
    bar.refresh()  # due: 12 s in, still 10 steps
    assert log.getvalue() == "sweep:  10% 10/100 steps [0:12 ETA 1:48, 1.2 s/step]\n"


def _relayed_job(key: str, total: int) -> str:
    """A job in a worker: its steps go to the parent's Tally through a Relay."""
    from rlu.progress import Relay

    with Relay(key, interval=0).start(total) as relay:
        for _ in range(total):
            relay.update(1)
    return key


@pytest.mark.parametrize("workers", [1, 2], ids=["in_process", "process_pool"])
def test_jobs_in_workers_add_up_in_one_tally(workers):
    from rlu.progress import Tally
    from rlu.workers import Backend, run_jobs

    log, clock = io.StringIO(), Clock()
    tally = Tally(3, "sweep", "steps", stream=log, clock=clock, mode="lines", interval=10,
                  heartbeat=False)  # fmt: skip
    seen = []

    def message(m):
        seen.append(m)
        clock.t += 1  # one second a message: lines every 10 of them
        assert tally.message(m)

    jobs = [(f"run{i}", 10 * (i + 1)) for i in range(3)]  # 10, 20 and 30 steps
    run_jobs(_relayed_job, jobs, Backend("local", workers), on_result=lambda i, key:
             tally.finish(key), on_message=message)  # fmt: skip
    tally.close()
    assert not tally.message(("something", "else"))  # another sender's message is left alone
    # every step reached the parent: start, 10 + 20 + 30 updates, close
    assert len(seen) == 3 * 2 + 60
    lines = log.getvalue().splitlines()
    assert lines[-1].startswith("sweep: 100% 60/60 steps [") and lines[-1].endswith("runs=3/3")
    assert len(lines) == 7 and "ETA" in lines[0]  # one every 10 s of 66, then the final one
    assert sum(line.startswith("sweep: 100%") for line in lines) == 1


def test_a_tally_estimates_the_runs_not_started_and_counts_a_failed_one_as_done():
    from rlu.progress import RELAY_TAG, Tally

    log, clock = io.StringIO(), Clock()
    tally = Tally(4, "sweep", "steps", estimate=100, stream=log, clock=clock, mode="lines",
                  heartbeat=False)  # fmt: skip
    assert tally.bar.total == 400
    tally.message((RELAY_TAG, "a", 0, 150))  # a run of 150 steps (its pre-training too)
    assert tally.bar.total == 150 + 3 * 100
    tally.message((RELAY_TAG, "b", 40, 100))
    tally.drop("b")  # failed after 40 steps: they count, its 60 left do not
    assert (tally.bar.n, tally.bar.total) == (40, 150 + 40 + 2 * 100)
    tally.message((RELAY_TAG, "a", 150, 150))
    tally.finish("a")
    tally.message((RELAY_TAG, "a", 10, 150))  # a late message of a finished run: ignored
    assert tally.bar.n == 190 and "runs=2/4" in tally.bar.render()
    tally.close()
