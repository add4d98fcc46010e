"""Rebuild rlu/resources/atari_best_behaviour.json from Dopamine's published DQN curves.

Usage: python scripts/atari_best_behaviour_from_dopamine.py DOPAMINE_GIT_DIR [--commit C] [--out F]

DOPAMINE_GIT_DIR is a clone of https://github.com/google/dopamine (a bare one will do). The
script reads ``baselines/atari/data/<game>.json`` at the commit with ``git show`` (numbers only:
each file is a list of ``{"Agent", "Iteration", "Value"}`` records), takes agent ``DQN``, splits
its records into runs where ``Iteration`` restarts at 0, and writes per game each run's best
iteration and the mean over the runs of those bests. See docs/atari_references.md.
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

from rlu.evaluation import reference  # noqa: E402
from rlu.tasks import ATARI_OFFLINE, ATARI_ONLINE  # noqa: E402

REPO_URL = "https://github.com/google/dopamine"
PATH = "baselines/atari/data/{game}.json"


def _git(repo: str, *args: str) -> str:
    return subprocess.run(["git", "-C", repo, *args], capture_output=True, text=True,
                          check=True).stdout  # fmt: skip


def runs_of(records: list[dict], agent: str = "DQN") -> list[list[float]]:
    """The agent's per-iteration values, one list per run (a run restarts at iteration 0)."""
    runs: list[list[float]] = []
    for r in records:
        if r.get("Agent") != agent:
            continue
        if r["Iteration"] == 0:
            runs.append([])
        if not runs or r["Iteration"] != len(runs[-1]):
            raise SystemExit(f"unexpected iteration order at {r}")
        runs[-1].append(float(r["Value"]))
    return runs


def provenance(commit: str, date: str) -> dict[str, str]:
    return {
        "source": f"Dopamine's published DQN baseline training curves: repository {REPO_URL}, "
        f"commit {commit} ({date}), files {PATH} (one per game; agent 'DQN'). Until commit "
        "8842298 (2021) the files were baselines/data/<game>.json, with the same DQN records "
        "(equal at commit 7ec9c15).",
        "layout": "Each file lists, per agent, 5 runs x 199 training iterations (0-198) of "
        "{Agent, Iteration, Value}, the runs concatenated one after the other (Iteration "
        "restarts at 0 for the next run).",
        "value": "A record's Value is the mean raw (unclipped) game score of one iteration's "
        "training episodes (250k agent steps, epsilon 0.01): Dopamine plots these baselines as "
        "train_episode_returns (dopamine/colab/load_statistics.ipynb), i.e. the returns of the "
        "policy that was collecting data at that point, what a dataset checkpoint holds.",
        "agent": "Dopamine DQN with sticky actions (repeat_action_probability 0.25), "
        "dopamine/agents/dqn/configs/dqn.gin (now dopamine/tf/agents/dqn/configs/dqn.gin): the "
        "configuration of batch_rl/baselines/configs/dqn.gin (google-research/batch_rl, commit "
        "8d967cc: the same values) that logged the DQN Replay Dataset, "
        "which RL Unplugged's Atari data is (epsilon_train 0.01, epsilon decay 250k steps, "
        "min replay 20k, target update 8k steps, centred RMSProp lr 2.5e-4, 200 iterations of "
        "250k agent steps, episodes capped at 27k agent steps, 4-frame repeat).",
        "statistic": "runs[r] = the best iteration of run r and its value; mean = the mean over "
        "the 5 runs of those bests (the reference); runs_std = their standard deviation "
        "(ddof 1).",
        "why": "RL Unplugged's appendix ('Atari Results Normalization') normalises by 'the best "
        "snapshot of online DQN that is used to generate the dataset' and prints no table. Each "
        "game's dataset is 5 runs, each with its own best snapshot, and the paper gives one "
        "number per game: the mean over the runs estimates a run's best snapshot, and it is "
        "the rule `rlu envs best-behaviour` applies to the release's atari_episodes_ordered "
        "files, so a recomputation from the release means the same thing. The maximum over "
        "runs would pick the luckiest of 995 noisy iteration means; a median would hide a run "
        "that failed (Zaxxon run 2, Freeway run 2), which is part of what the data holds.",
        "caveats": "Dopamine's published runs use the same agent and configuration as the "
        "runs that generated the release, but are not those runs. The best of 199 noisy "
        "iteration means is biased upwards against any one checkpoint's expected return. "
        "Replace these numbers with the release's own with `rlu envs best-behaviour`.",
        "units": "raw game score per episode (no reward clipping), the scale rlu's Atari "
        "evaluation reports",
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("repo", help="git directory of a google/dopamine clone")
    p.add_argument("--commit", default="HEAD")
    p.add_argument("--out", default=str(ROOT / "rlu/resources/atari_best_behaviour.json"))
    args = p.parse_args()
    commit = _git(args.repo, "rev-parse", args.commit).strip()
    date = _git(args.repo, "log", "-1", "--format=%cI", commit).strip()
    scores = {}
    for game in ATARI_ONLINE + ATARI_OFFLINE:
        path = PATH.format(game=game.lower())
        runs = runs_of(json.loads(_git(args.repo, "show", f"{commit}:{path}")))
        if len(runs) != 5 or any(len(r) != len(runs[0]) for r in runs):
            raise SystemExit(
                f"{path}: expected 5 runs of equal length, got {[len(r) for r in runs]}"
            )
        per_run = {}
        for i, values in enumerate(runs, start=1):
            best = int(np.argmax(values))  # ties: the earliest iteration
            per_run[str(i)] = {"iteration": best, "mean": values[best]}
        bests = [r["mean"] for r in per_run.values()]
        scores[f"atari/{game}"] = {
            "mean": float(np.mean(bests)),
            "runs": per_run,
            "runs_std": float(np.std(bests, ddof=1)),
            "iterations": len(runs[0]),
            "file": path,
        }
    doc = {"format": reference.FORMAT, "provenance": provenance(commit, date),
           "scores": scores}  # fmt: skip
    reference.write(args.out, doc)
    print(f"wrote {len(scores)} games to {args.out} (google/dopamine {commit[:12]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
