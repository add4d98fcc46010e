"""rliable's performance profiles and probability of improvement: rlu's vectorised computation
(``rlu.report.profiles``) against rliable's own on the same scores, in one process;
prints both timings, their ratio and whether every number agrees.

    .venv/bin/python bench/report_profiles.py                       # 5 agents, 9 tasks, 3 seeds
    .venv/bin/python bench/report_profiles.py --tasks 46 --seeds 5 --reps 2000

rliable (``rliable==1.2.0`` with ``arch==7.2.0``, ``pandas==2.3.3``: the dev extra) computes
each bootstrap replicate in Python, one scipy Mann-Whitney call per task and pair for the
probability of improvement; rlu draws the same resamples (``np.random.RandomState(0)``; rliable
after ``np.random.seed(0)``) and computes every replicate at once. The load average is printed.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--agents", type=int, default=5)
    ap.add_argument("--tasks", type=int, default=9)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--reps", type=int, default=2000)
    args = ap.parse_args()
    from rliable import library as rly
    from rliable import metrics

    from rlu.report.profiles import performance_profile, probability_of_improvement

    rng = np.random.default_rng(0)
    scores = {f"agent{i}": rng.normal(400 + 50 * i, 150, (args.seeds, args.tasks))
              for i in range(args.agents)}  # fmt: skip
    names = list(scores)
    pairs = {
        f"{x},{y}": (scores[x], scores[y]) for i, x in enumerate(names) for y in names[i + 1 :]
    }
    taus = np.linspace(0, 1000, 101)
    print(f"{args.agents} agents, {args.tasks} tasks, {args.seeds} seeds, {args.reps} replicates; "
          f"load {os.getloadavg()[0]:.1f}")  # fmt: skip
    for what, ours, theirs in (
        ("performance profiles",
         lambda: performance_profile(scores, taus, reps=args.reps, random_state=0),
         lambda: rly.create_performance_profile(scores, taus, reps=args.reps)),
        ("probability of improvement",
         lambda: probability_of_improvement(pairs, reps=args.reps, random_state=0),
         lambda: rly.get_interval_estimates({k: list(v) for k, v in pairs.items()},
                                            metrics.probability_of_improvement, reps=args.reps)),
    ):  # fmt: skip
        t = time.process_time()
        p1, c1 = ours()
        t_rlu = time.process_time() - t
        np.random.seed(0)
        t = time.process_time()
        p2, c2 = theirs()
        t_rliable = time.process_time() - t
        same = all(np.allclose(np.ravel(p1[k]), np.ravel(p2[k]), rtol=0, atol=1e-12)
                   and np.allclose(np.ravel(c1[k]), np.ravel(c2[k]), rtol=0, atol=1e-12)
                   for k in p1)  # fmt: skip
        print(f"{what}: rlu {t_rlu:.2f} CPU-s, rliable {t_rliable:.2f} CPU-s, "
              f"{t_rliable / t_rlu:.0f}x; every number the same: {same}")  # fmt: skip


if __name__ == "__main__":
    main()
