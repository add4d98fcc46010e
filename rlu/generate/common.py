"""What the three recipes share: success rule, selection, work folder, merge, progress, provenance.

The recipes (``recipe``: D4PG / DQN training runs; ``policy``: a user's policy; ``rwrl``: fixed
snapshots) are peers that import this module, never each other. The paper's selection (SPEC §4):
record every episode of whole runs, keep a third of the *successful* ones (the paper: "we further
reduce the number of successful episodes by 2/3"), then sub-sample uniformly to the task's
episode count, keeping the order of recording.

Success, per domain (``success_rule``):

- control suite: the episode return is at least 800, i.e. 80 % of the maximum 1000 (every task
  rewards at most 1 per step over 1000 steps); D4PG's converged returns on the tasks the paper
  calls solved lie above it;
- Atari: no episode counts as successful: the paper keeps DQN's whole replay (no reduction);
- locomotion: the episode reached its time limit (the walker did not fall).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data import DatasetWriter, open_dataset
from rlu.data.episode import Segment
from rlu.generate.recorder import schema_for
from rlu.tasks import TaskSpec
from rlu.types import RluError

CONTROL_SUCCESS_RETURN = 800.0


def success_rule(task: TaskSpec) -> str:
    if task.domain == "atari":
        return "none: Atari keeps every recorded episode (the paper keeps DQN's replay)"
    if task.domain == "locomotion":
        return "the episode reached its time limit (the walker did not fall or fail: not terminal)"
    return f"episode_return >= {CONTROL_SUCCESS_RETURN:g} (80% of the maximum 1000)"


def is_success(task: TaskSpec, returns: np.ndarray, terminal: np.ndarray) -> np.ndarray:
    """``terminal``: whether each episode ended in a terminal state (not a time limit)."""
    if task.domain == "atari":
        return np.zeros(returns.shape, bool)
    if task.domain == "locomotion":
        return ~terminal
    return returns >= CONTROL_SUCCESS_RETURN


def select_episodes(
    success: np.ndarray, target: int | None, rng: np.random.Generator
) -> tuple[np.ndarray, dict[str, int]]:
    """Indices kept: a third (rounded up) of the successful episodes, then a uniform sub-sample
    down to ``target``; sorted, so the recording order stays."""
    idx = np.arange(success.size)
    good = idx[success]
    keep_good = rng.choice(good, (good.size + 2) // 3, replace=False) if good.size else good
    pool = np.sort(np.concatenate([idx[~success], keep_good]))
    if target is not None and pool.size > target:
        pool = np.sort(rng.choice(pool, target, replace=False))
    counts = {
        "recorded": int(success.size),
        "successful": int(good.size),
        "successful_kept_after_third": int(keep_good.size),
        "target": -1 if target is None else int(target),
        "kept": int(pool.size),
        "kept_successful": int(success[pool].sum()),
    }
    return pool, counts


def paper_count(task: TaskSpec) -> int | None:
    """The paper's episode count for the task (None: keep everything, as Atari's replay)."""
    if task.domain == "atari":
        return None
    return int(task.episodes[""]) if "" in task.episodes else None


def command_line(task_id: str, scale: str, runs: int, seed: int) -> str:
    """The command recorded in the manifest (``--out`` left out: it does not change the data)."""
    return f"rlu generate {task_id} --scale {scale} --seeds {runs} --seed {seed}"


def versions(task: TaskSpec) -> dict[str, str]:
    """Versions of the packages the bytes depend on (recorded in the provenance)."""
    from importlib import metadata

    sim = ["ale-py"] if task.domain == "atari" else ["dm-control", "mujoco"]
    out = {}
    for n in ["numpy", "torch", *sim]:
        try:
            out[n] = metadata.version(n)
        except metadata.PackageNotFoundError:
            pass
    return out


def open_work(work: Path, settings: dict[str, Any], resume_command: str) -> None:
    """Create the work folder with ``settings.json``, or check that the interrupted generation
    there used the same settings (a resumed run must give the bytes of an uninterrupted one)."""
    path = work / "settings.json"
    if path.exists():
        before = json.loads(path.read_text())
        if before != settings:
            diff = sorted(k for k in settings.keys() | before.keys()
                          if before.get(k) != settings.get(k))  # fmt: skip
            raise RluError(
                f"{work} holds an interrupted generation with other settings ({', '.join(diff)}); "
                f"re-run its command ({resume_command}) to resume it, or remove {work}"
            )
        return
    work.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(".settings.json.tmp")
    tmp.write_text(json.dumps(settings, indent=1, sort_keys=True))
    tmp.replace(path)


def merge_runs(task: TaskSpec, work: Path, runs: int, settings: dict[str, Any],
               target: int | None, seed: int, out: Path, command: str,
               policies: str | None = None) -> Path:  # fmt: skip
    """Select episodes from every run's parts under ``work`` and write the final dataset. The
    provenance keeps every recorded episode's return and length per run (``runs``): the runs'
    learning curves, of which the dataset keeps a sub-sample (``rlu.generate.curves``).
    ``policies`` (the weights' dtype; None: the recipe keeps none): attach the behaviour policy
    of every (run, checkpoint) the kept episodes name, from ``work/run_*/policies/``."""
    parts, curves = [], []
    for r in range(runs):
        run_parts = sorted((work / f"run_{r:03d}").glob("part_*"))
        mine = [open_dataset(p) for p in run_parts if (p / "manifest.json").exists()]
        parts += mine
        curves.append({
            "run": r,
            "episode_return": [round(float(x), 3) for p in mine
                               for x in np.asarray(p.metadata("episode_return"))],
            "episode_steps": [int(n) - 1 for p in mine for n in np.asarray(p.length)],
        })  # fmt: skip
    returns = np.concatenate([np.asarray(p.metadata("episode_return")) for p in parts])
    terminal = np.concatenate(
        [np.asarray(p.column("is_terminal"))[p.start + p.length - 1] for p in parts]
    )
    where = [(i, j) for i, p in enumerate(parts) for j in range(len(p))]
    rng = np.random.default_rng([seed, 3])
    keep, counts = select_episodes(is_success(task, returns, terminal), target, rng)
    provenance = {
        "generator": "rlu generate",
        "command": command,
        "settings": settings,
        "selection": counts,
        "versions": versions(task),
        "runs": curves,
    }
    attach: dict[str, Path] = {}
    if policies is not None:
        from rlu.generate.policies import snapshot_files

        run_of = np.concatenate([np.asarray(p.metadata("run")) for p in parts])
        checkpoint_of = np.concatenate([np.asarray(p.metadata("checkpoint")) for p in parts])
        named = np.stack([run_of[keep], checkpoint_of[keep]], axis=1).tolist()
        attach = snapshot_files(work, [(r, c) for r, c in named])
        provenance["policies"] = {
            "kept": "the behaviour policy of every (run, checkpoint) the episodes name, taken "
            "before the checkpoint's first episode: policies/run_RRR/checkpoint_CCCCC.npz "
            "(acting network weights, no pickle) + .json (agent config); rlu.generate.policies",
            "dtype": policies,
            "count": len(attach) // 2,
        }
    with DatasetWriter(out, schema_for(task), provenance=provenance) as w:
        for k in keep.tolist():
            i, j = where[k]
            w.append(parts[i].segment(j))
        for rel, src in attach.items():
            w.attach(rel, src)
    return out


class Progress:
    """A one-line progress bar on stderr (one line per run when stderr is not a terminal)."""

    def __init__(self, total: int, label: str, enabled: bool = True):
        self.total, self.label, self.enabled = total, label, enabled
        self.done, self.t0 = 0, time.perf_counter()
        self.latest: dict[int, int] = {}  # run -> its last episode number (1-based)
        self.tty = sys.stderr.isatty()

    def update(self, run: int, episode: int, seg: Segment) -> None:
        self.report(run, episode, float(seg.metadata["episode_return"]))

    def report(self, run: int, episode: int, episode_return: float) -> None:
        # episodes played, counted from each run's episode number: a resumed run's first report
        # counts the episodes it played before the interruption too
        first = run not in self.latest  # this run's first episode here, fresh or resumed
        self.latest[run] = episode
        self.done = sum(self.latest.values())
        if not self.enabled:
            return
        frac = self.done / self.total if self.total else 0.0  # 0: a budget in env steps
        bar = "#" * int(30 * min(1.0, frac))
        el = time.perf_counter() - self.t0
        msg = (
            f"{self.label} [{bar:<30}] {self.done}/{self.total or '?'} episodes  run {run} "
            f"ep {episode} return {episode_return:8.1f}  {el:6.0f}s"
        )
        if self.tty:
            print("\r" + msg, end="", file=sys.stderr, flush=True)
        elif first or self.done == self.total or self.done % 10 == 0:
            print(msg, file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.enabled and self.tty:
            print(file=sys.stderr)
