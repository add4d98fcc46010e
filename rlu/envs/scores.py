"""Random-policy returns per task, measured with rlu's own envs and stored with provenance.

Atari normalisation (paper appendix: ``100 * (score - random) / (best_behaviour - random)``)
needs a random score per game. The paper gives none in numbers, so rlu measures them with the
same envs the agents are evaluated in (uniform random actions, sticky actions 0.25, the
episode cap recorded in the provenance) and ships the result as ``rlu/resources/
random_scores.json``. ``rlu envs random-scores`` re-measures and writes such a file.

File layout::

    {"format": "rlu.random_scores/1",
     "provenance": {"date", "code_version", "seed", "episodes", "settings", "packages", ...,
                    "runs": [{"date", "code_version", "episodes", "seed", "workers",
                              "tasks", "cpu_seconds", "wall_seconds", "steps"}, ...]},
     "scores": {"atari/Pong": {"mean", "std", "episodes", "returns", "lengths", "challenge",
                               "settings", "seed", "date", "code_version", "cpu_seconds",
                               "steps"},
                "rwrl/walker_walk@easy": {...}, ...}}

The file-level fields are the first run's; ``runs`` lists every run that measured entries
(``--resume`` adds tasks to an existing file), and an entry's own ``date`` / ``code_version`` /
``seed`` / ``cpu_seconds`` (process CPU time of the measurement) say which run measured it and
at what cost. Entries without them were measured by the first run, with its seed.

Keys are task ids, with ``@<challenge>`` for RWRL challenges other than ``none``.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import subprocess
import time
from collections.abc import Callable, Iterable
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from rlu.files import read_json, write_json
from rlu.types import FormatError, RluError

FORMAT = "rlu.random_scores/1"


def score_key(task_id: str, challenge: str = "none") -> str:
    return task_id if challenge == "none" else f"{task_id}@{challenge}"


def random_returns(
    task_id: str,
    episodes: int,
    seed: int = 0,
    challenge: str = "none",
    **settings: Any,
) -> tuple[list[float], list[int]]:
    """Undiscounted returns and lengths of ``episodes`` uniform-random episodes.

    Atari returns sum ``info["raw_reward"]`` (the unclipped game score). Episode i resets with
    seed ``seed + i``; the action sampler is seeded with ``seed``.
    """
    from rlu.envs import make_env

    env = make_env(task_id, seed=seed, challenge=challenge, **settings)
    env.action_space.seed(seed)
    returns, lengths = [], []
    try:
        for i in range(episodes):
            env.reset(seed=seed + i)
            total, n, done = 0.0, 0, False
            while not done:
                _, r, term, trunc, info = env.step(env.action_space.sample())
                total += float(info.get("raw_reward", r))
                n += 1
                done = term or trunc
            returns.append(total)
            lengths.append(n)
    finally:
        env.close()
    return returns, lengths


def code_version() -> str:
    import rlu

    try:
        root = Path(__file__).resolve().parents[2]
        rev = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        rev = ""
    return f"rlu {rlu.__version__}" + (f" (git {rev})" if rev else "")


def _packages() -> dict[str, str]:
    from importlib import metadata

    out = {}
    for name in ("ale-py", "dm-control", "mujoco", "gymnasium", "opencv-python-headless"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return out


def measure_task(
    task_id: str, challenge: str, settings: dict[str, Any], episodes: int, seed: int
) -> dict[str, Any]:
    """One task's entry: ``episodes`` random episodes with their cost (process CPU seconds)."""
    cpu0 = time.process_time()
    returns, lengths = random_returns(task_id, episodes, seed, challenge, **settings)
    return {
        "mean": float(np.mean(returns)),
        "std": float(np.std(returns)),
        "episodes": len(returns),
        "returns": returns,
        "lengths": lengths,
        "challenge": challenge,
        "settings": settings,
        "seed": seed,
        # A resumed file gathers tasks measured by different runs: each entry says its own.
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "code_version": code_version(),
        "cpu_seconds": round(time.process_time() - cpu0, 2),
        "steps": int(sum(lengths)),
    }


def is_complete(entry: dict[str, Any], episodes: int, seed: int, settings: dict[str, Any],
                file_seed: int | None = None) -> bool:  # fmt: skip
    """Whether a stored entry already holds ``episodes`` or more episodes of the same measurement
    (seed and settings): ``--resume`` keeps those and re-measures the rest."""
    return (
        int(entry.get("episodes", 0)) >= episodes
        and entry.get("seed", file_seed) == seed
        and dict(entry.get("settings", {})) == dict(settings)
    )


def measure(
    tasks: Iterable[tuple[str, str, dict[str, Any]]],
    episodes: int,
    seed: int = 0,
    progress: Callable[[str, dict[str, Any]], None] | None = None,
    existing: dict[str, Any] | None = None,
    workers: int = 1,
) -> dict[str, Any]:
    """Measure every ``(task_id, challenge, settings)``; returns the file's dict.

    ``existing`` (a loaded file) is extended: a task already in it with at least ``episodes``
    episodes of the same seed and settings is kept, the others are (re-)measured, so an
    interrupted measurement resumes task by task. ``workers`` > 1 measures tasks in that many
    spawned processes; an entry is a function of (task, episodes, seed, settings) alone, so the
    numbers do not depend on it. ``progress(key, entry)`` runs in this process after each task.
    """
    if workers < 1:
        raise RluError(f"workers={workers}: give at least 1 process")
    doc = existing or {
        "format": FORMAT,
        "provenance": {
            "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "code_version": code_version(),
            "seed": seed,
            "episodes": episodes,
            "policy": "uniform random actions (env.action_space.sample(), seeded)",
            "packages": _packages(),
            "cpu_count": os.cpu_count(),
        },
        "scores": {},
    }
    file_seed = doc["provenance"].get("seed")
    todo = [
        (score_key(t, c), t, c, s)
        for t, c, s in tasks
        if score_key(t, c) not in doc["scores"]
        or not is_complete(doc["scores"][score_key(t, c)], episodes, seed, s, file_seed)
    ]
    if not todo:
        return doc
    run: dict[str, Any] = {
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "code_version": code_version(),
        "episodes": episodes,
        "seed": seed,
        "workers": workers,
        "tasks": [],
        "cpu_seconds": 0.0,
        "wall_seconds": 0.0,
        "steps": 0,
    }
    doc["provenance"].setdefault("runs", []).append(run)
    start = time.monotonic()

    def done(key: str, entry: dict[str, Any]) -> None:
        doc["scores"][key] = entry
        run["tasks"].append(key)
        run["cpu_seconds"] = round(run["cpu_seconds"] + entry["cpu_seconds"], 2)
        run["steps"] += entry["steps"]
        run["wall_seconds"] = round(time.monotonic() - start, 1)
        if progress is not None:
            progress(key, entry)

    from rlu.workers import Backend, run_jobs

    # one process per task at once (spawned, dying with this one: rlu.workers), or this one
    keys = [key for key, *_ in todo]
    jobs = [(t, c, s, episodes, seed) for _, t, c, s in todo]
    run_jobs(measure_task, jobs, Backend(workers=workers), lambda i, e: done(keys[i], e))
    return doc


def write(doc: dict[str, Any], path: str | os.PathLike) -> None:
    """Write atomically (temp file + rename): a crash never leaves half a file."""
    write_json(path, doc, indent=1)


def load(path: str | os.PathLike | None = None) -> dict[str, Any]:
    """The shipped random scores (or the file at ``path``)."""
    if path is None:
        text = resources.files("rlu").joinpath("resources/random_scores.json").read_text()
        where = "rlu/resources/random_scores.json"
        doc = json.loads(text)
    else:  # a file of the user's: bounded, a regular file, JSON
        where = str(path)
        doc = read_json(path, fix="check the path, or re-run `rlu envs random-scores`")
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or "scores" not in doc:
        raise FormatError(f"{where}: not an {FORMAT} file; re-run `rlu envs random-scores`")
    return doc


def random_score(task_id: str, challenge: str = "none", path: str | None = None) -> float:
    """Mean random-policy return of a task (Atari: the raw game score)."""
    doc = load(path)
    key = score_key(task_id, challenge)
    try:
        return float(doc["scores"][key]["mean"])
    except KeyError:
        raise RluError(
            f"no random score for {key!r} in {path or 'rlu/resources/random_scores.json'}; "
            f"measure it with: rlu envs random-scores --task {task_id}"
        ) from None
