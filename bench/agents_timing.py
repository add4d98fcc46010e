"""Timing shared by bench/agents_continuous.py and bench/agents_discrete.py (not a bench itself).

A contestant is one learner: ``sample()`` draws a batch from its own sampler, ``update(batch)``
runs one learner step on it. Each contestant is timed two ways in the same run:

- "sample + update": ``update(sample())``, what a training loop pays per step;
- "update only": ``update(batch)`` on batches it drew before timing (cycled), the learner alone.

Many short rounds interleave every (contestant, way) pair in a fresh random order each round, and
every update is timed on its own: the rate is one over the median time of an update, so a burst
of load from elsewhere on a shared machine moves a few updates of every contestant, not the
figure of one. Rates are updates per second of process CPU time (one torch thread by default: it
equals wall time on an idle machine and is far less disturbed by neighbours than the wall clock)
and of wall time; ratios are of the CPU rates. The load average is printed before and after each
agent.
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

MODES = ("sample + update", "update only")


@dataclass
class Contestant:
    """One learner: its own sampler and its own update."""

    sample: Callable[[], Any]
    update: Callable[[Any], Any]
    note: str = ""
    pool: list[Any] = field(default_factory=list)
    """Batches drawn before timing, for "update only"."""


def load_line() -> str:
    one, five, _ = os.getloadavg()
    cores = len(os.sched_getaffinity(0))
    return f"load average {one:.2f} (1 min), {five:.2f} (5 min) on {cores} cores"


def cpu_line() -> str:
    """The CPU the figures come from: ratios between libraries move with its vector units and
    caches, so each run names it."""
    import torch

    model = "unknown CPU"
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")),
                         model)  # fmt: skip
    except OSError:
        pass
    return f"{model}, torch CPU capability {torch.backends.cpu.get_cpu_capability()}"


def time_contestants(
    contestants: dict[str, Contestant], rounds: int, block: float, warmup: int, pool: int = 4
) -> dict[str, dict[str, tuple[float, float]]]:
    """{name: {mode: (wall updates/s, updates per CPU-second)}}, from the median time of one
    update over every update timed. Each round runs every (contestant, way) pair in a fresh
    random order for about ``block`` CPU-seconds (at least two updates, sized from the
    warm-up); every update is timed on its own, so a burst of load from elsewhere shifts a few
    updates of every contestant, not the median of one."""
    updates = {}
    for name, c in contestants.items():
        c.pool = [c.sample() for _ in range(pool)]
        for i in range(warmup):
            c.update(c.sample() if i % 2 else c.pool[i % pool])
        c0 = time.process_time()
        c.update(c.sample())
        updates[name] = max(2, round(block / max(time.process_time() - c0, 1e-6)))
    pairs = [(name, mode) for name in contestants for mode in MODES]
    wall: dict[tuple[str, str], list[float]] = {p: [] for p in pairs}
    cpu: dict[tuple[str, str], list[float]] = {p: [] for p in pairs}
    order = np.random.default_rng(0)
    for _ in range(rounds):
        for k in order.permutation(len(pairs)):
            name, mode = pairs[k]
            c, w, t = contestants[name], wall[pairs[k]], cpu[pairs[k]]
            for i in range(updates[name]):
                w0, c0 = time.perf_counter(), time.process_time()
                if mode == MODES[0]:
                    c.update(c.sample())
                else:
                    c.update(c.pool[i % len(c.pool)])
                t.append(time.process_time() - c0)
                w.append(time.perf_counter() - w0)
    return {
        name: {
            mode: (
                1.0 / max(statistics.median(wall[name, mode]), 1e-9),
                1.0 / max(statistics.median(cpu[name, mode]), 1e-9),
            )
            for mode in MODES
        }
        for name in contestants
    }


RATIOS = (
    ("rlu", "minimal loop", 0.95),
    ("rlu", "d3rlpy", 1.5),
    ("rlu", "d3rlpy same net", 1.5),
    ("rlu bf16", "d3rlpy", 1.5),
    ("rlu bf16", "d3rlpy same net", 1.5),
)
"""(numerator, denominator, target on sample + update) printed where both were timed."""


def report(
    title: str, rates: dict[str, dict[str, tuple[float, float]]], notes: dict[str, str]
) -> dict[str, dict[str, float]]:
    """Print the figures and the ratios of :data:`RATIOS`; return the ratios
    ({"a / b": {mode: value}})."""
    print(f"\n{title}")
    for name, note in notes.items():
        print(f"  {name}: {note}")
    head = "".join(f"{m:>26s}" for m in MODES)
    print(f"  {'updates/s: CPU-s (wall)':24s}{head}")
    for name, by_mode in rates.items():
        cells = "".join(f"{by_mode[m][1]:15.1f} ({by_mode[m][0]:7.1f})" for m in MODES)
        print(f"  {name:24s}{cells}")
    ratios: dict[str, dict[str, float]] = {}
    for a, b, target in RATIOS:
        if a not in rates or b not in rates:
            continue
        label = f"{a} / {b}"
        ratios[label] = {m: rates[a][m][1] / rates[b][m][1] for m in MODES}
        cells = "".join(f"{ratios[label][m]:25.2f}x" for m in MODES)
        print(f"  {label:24s}{cells}   (target >= {target:g}x sample + update)")
    return ratios


def bf16(update):
    """``update`` under CPU bf16 autocast (matrix products and convolutions in bfloat16, the
    parameters and Adam in float32): an opt-in that changes the numbers, timed for comparison."""
    import torch

    def run(batch):
        # cache off, as ``rlu.devices.numerics`` runs an update: with the cache, forwards after
        # an optimiser step in the same update read the weights from before it
        with torch.autocast("cpu", dtype=torch.bfloat16, cache_enabled=False):
            return update(batch)

    return run


def summary(results: dict[str, dict[str, dict[str, float]]]) -> None:
    print(f"\nsummary (ratios of updates per CPU-second); {load_line()}")
    for label, ratios in results.items():
        cells = "; ".join(
            f"{k}: {v[MODES[0]]:.2f}x sample + update, {v[MODES[1]]:.2f}x update only"
            for k, v in ratios.items()
        )
        print(f"  {label:20s} {cells}")
