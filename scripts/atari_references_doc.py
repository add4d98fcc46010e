"""Print the tables of docs/atari_references.md from the shipped Atari references.

Usage: python scripts/atari_references_doc.py [--old-commit REV]

Reads rlu/resources/random_scores.json, atari_best_behaviour.json and paper_results.json; with
``--old-commit`` also the two reference files as they were at that commit of this repository
(``git show``), for the old-versus-new columns. tests/evaluation/test_atari_references.py
recomputes the medians table and checks it against the docs.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rlu.envs import scores as random_scores  # noqa: E402
from rlu.evaluation import reference  # noqa: E402
from rlu.report import load_paper_results  # noqa: E402
from rlu.tasks import ATARI_OFFLINE, ATARI_ONLINE  # noqa: E402

AGENTS = ("BC", "DQN", "IQN", "BCQ", "REM")


def references(random_doc: dict, best_doc: dict, combine: str = "mean") -> tuple[dict, dict]:
    """({game: random mean}, {game: best}) with the runs' bests combined by ``combine``."""
    rnd = {g: random_doc["scores"][f"atari/{g}"]["mean"] for g in ATARI_ONLINE + ATARI_OFFLINE}
    best = {}
    for g in ATARI_ONLINE + ATARI_OFFLINE:
        e = best_doc["scores"][f"atari/{g}"]
        runs = [r["mean"] for r in e.get("runs", {}).values()] or [e["mean"]]
        best[g] = e["mean"] if combine == "mean" else float(getattr(np, combine)(runs))
    return rnd, best


def medians(rnd: dict, best: dict) -> dict:
    return reference.paper_medians(
        load_paper_results()["atari"], rnd, best, ATARI_ONLINE, ATARI_OFFLINE
    )


def _old(commit: str, name: str) -> dict:
    text = subprocess.run(["git", "-C", str(ROOT), "show", f"{commit}:rlu/resources/{name}"],
                          capture_output=True, text=True, check=True).stdout  # fmt: skip
    return json.loads(text)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--old-commit", help="a commit of this repository with the old references")
    args = p.parse_args()
    rdoc, bdoc = random_scores.load(), reference.load()
    new = medians(*references(rdoc, bdoc))
    old = None
    if args.old_commit:
        ordoc, obdoc = (_old(args.old_commit, f"{n}.json") for n in
                        ("random_scores", "atari_best_behaviour"))  # fmt: skip
        old = medians(*references(ordoc, obdoc))
    print("| agent | online, old | offline, old | online, new | offline, new |")
    print("|---|---|---|---|---|")
    for a in AGENTS:
        o = old[a] if old else {"online": float("nan"), "offline": float("nan")}
        n = new[a]
        print(f"| {a} | {o['online']:.1f} | {o['offline']:.1f} | {n['online']:.1f} | "
              f"{n['offline']:.1f} |")  # fmt: skip
    print()
    print("| runs' bests combined by | " + " | ".join(f"{a} on / off" for a in AGENTS) + " |")
    print("|---|" + "---|" * len(AGENTS))
    for combine in ("mean", "median", "max", "min"):
        m = medians(*references(rdoc, bdoc, combine))
        cells = " | ".join(f"{m[a]['online']:.1f} / {m[a]['offline']:.1f}" for a in AGENTS)
        print(f"| {combine} | {cells} |")
    print()
    rnd, best = references(rdoc, bdoc)
    keep = [g for g in rnd if not reference.small_denominator(
        rnd[g], rdoc["scores"][f"atari/{g}"]["std"], best[g])]  # fmt: skip
    m = reference.paper_medians(load_paper_results()["atari"], rnd, best,
                                [g for g in ATARI_ONLINE if g in keep],
                                [g for g in ATARI_OFFLINE if g in keep])  # fmt: skip
    print("new references, flagged games left out: " + "; ".join(
        f"{a} {m[a]['online']:.1f} / {m[a]['offline']:.1f}" for a in AGENTS))  # fmt: skip
    print()
    print(
        "| game | split | random (n) | std | old random (5) | best (mean of 5 runs) | runs' "
        "bests, min to max | old best (run 1) | best - random | separation | ref. SE (pts) | "
        "flag |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for g in ATARI_ONLINE + ATARI_OFFLINE:
        t = f"atari/{g}"
        r, b = rdoc["scores"][t], bdoc["scores"][t]
        runs = [x["mean"] for x in b["runs"].values()]
        chk = reference.denominator_check(r["mean"], r["std"], r["episodes"], b["mean"], runs)
        o_r = ordoc["scores"][t]["mean"] if old else float("nan")
        o_b = obdoc["scores"][t]["mean"] if old else float("nan")
        split = "online" if g in ATARI_ONLINE else "offline"
        print(f"| {g} | {split} | {r['mean']:.1f} ({r['episodes']}) | {r['std']:.1f} | "
              f"{o_r:.1f} | {b['mean']:.1f} | {min(runs):.1f} to {max(runs):.1f} | {o_b:.1f} | "
              f"{chk['denominator']:.1f} | {chk['separation']:.2f} | "
              f"{chk['reference_se']:.1f} | {'†' if chk['flagged'] else ''} |")  # fmt: skip
    cost = [rdoc["scores"][f"atari/{g}"] for g in ATARI_ONLINE + ATARI_OFFLINE]
    cpu = [e.get("cpu_seconds", float("nan")) for e in cost]
    steps = sum(e.get("steps", 0) for e in cost)
    print()
    print(f"cost: {np.nansum(cpu):.0f} CPU s in all, per game {np.nanmin(cpu):.0f}-"
          f"{np.nanmax(cpu):.0f} (median {np.nanmedian(cpu):.0f}); {steps} agent steps, "
          f"{steps / np.nansum(cpu):.0f} steps per CPU second")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
