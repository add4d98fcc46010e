"""The Atari normalisation reference: the best snapshot of the DQN that generated the data.

RL Unplugged's appendix ("Atari Results Normalization") scores a game as
``100 * (score - random) / (best_score - random)``, where ``best_score`` is "the best snapshot of
online DQN that is used to generate the dataset" (following Agarwal et al. 2020). The paper
prints no table of these numbers. rlu ships one, ``rlu/resources/atari_best_behaviour.json``,
and this module reads it and recomputes it from release files a user has downloaded.

File layout (``FORMAT``)::

    {"format": "rlu.atari_best_behaviour/1",
     "provenance": {"source", "statistic", "why", ...},
     "scores": {"atari/Pong": {"mean": 17.4, "runs": {"1": {"iteration", "mean"}, ...}, ...}}

``mean`` is the reference score; ``runs`` holds each run's best, the other fields of an entry say
where it came from. The shipped file is built from Dopamine's five published sticky-action DQN
runs per game (``scripts/atari_best_behaviour_from_dopamine.py``; docs/atari_references.md).

Recomputing from the release (``best_behaviour_from_release``; the command
``rlu envs best-behaviour``): the ``atari_episodes_ordered`` files hold one shard per checkpoint
(1M agent steps of the online run, in time order) and each episode's raw ``episode_return`` and
``checkpoint_idx``. A run's best snapshot is the checkpoint with the highest mean raw episode
return; a game's reference is that number averaged over the runs given (one run: that run's).
Only the small scalar fields of each record are decoded, never the PNG frames.

Small denominators (``denominator_check``): where ``best - random`` is small against the spread
of random play's episode returns, a normalised score measures the luck of a few episodes more
than the agent; the report flags such games (the rule and why: ``SPREAD_K``).
"""

from __future__ import annotations

import json
import os
import re
from collections import defaultdict
from collections.abc import Mapping, Sequence
from importlib import resources
from typing import Any

import numpy as np

from rlu.files import read_json, write_json
from rlu.types import FormatError, RluError

FORMAT = "rlu.atari_best_behaviour/1"
SPREAD_K = 2.0
"""A game's denominator ``best - random`` is small when it is under ``SPREAD_K`` standard
deviations of random play's episode returns: the best snapshot's mean then lies inside the
range a single random episode reaches (mean +- 2 std holds about 95 % of a normal spread), and
a random episode 2 std above its mean already scores 100 %. k = 2 is the conventional two-sigma
line. On the shipped references the separations ``(best - random) / std`` are 1.51 or less for
four games (TimePilot, Centipede, Gravitar, IceHockey) and 4.68 or more for the other 42, so any
k from 1.6 to 4.6 flags the same four (docs/atari_references.md)."""
RESOURCE = "rlu/resources/atari_best_behaviour.json"
_RUN_RE = re.compile(r"run_(\d+)")


def load(path: str | os.PathLike | None = None) -> dict[str, Any]:
    """The shipped reference (or the file at ``path``), checked for its format."""
    if path is None:
        text = resources.files("rlu").joinpath("resources/atari_best_behaviour.json").read_text()
        where = RESOURCE
        doc = json.loads(text)
    else:  # a file of the user's: bounded, a regular file, JSON
        where = str(path)
        doc = read_json(path, fix="check the path, or rewrite it with rlu envs best-behaviour")
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or "scores" not in doc:
        raise FormatError(
            f"{where}: not an {FORMAT} file (field 'format'); write one with "
            "rlu envs best-behaviour"
        )
    for key, entry in doc["scores"].items():
        if not isinstance(entry, Mapping) or not isinstance(entry.get("mean"), int | float):
            raise FormatError(f"{where}: scores[{key!r}] needs a numeric 'mean'")
    return doc


def best_behaviour(task_id: str, path: str | os.PathLike | None = None) -> float:
    """The reference score of one Atari task id (``atari/Pong``)."""
    doc = load(path)
    try:
        return float(doc["scores"][task_id]["mean"])
    except KeyError:
        raise RluError(
            f"no best-behaviour score for {task_id!r} in {path or RESOURCE}; recompute it from "
            f"release files with: rlu envs best-behaviour --task {task_id} --src ROOT"
        ) from None


def _scalar(cols: Mapping[str, Any], key: str, where: str) -> np.ndarray:
    from rlu.codecs import example as ex

    col = cols.get(key)
    if col is None:
        raise FormatError(
            f"{where}: feature {key!r} is missing (found {sorted(cols)}); best-behaviour scores "
            "are read from atari_episodes_ordered files"
        )
    if isinstance(col, ex.BytesColumn) or col.dtype == object or col.ndim != 2 or col.shape[1] != 1:
        raise FormatError(f"{where}: feature {key!r} must hold one number per record")
    return col[:, 0]


def checkpoint_returns(path: str | os.PathLike, verify: bool = True) -> dict[int, list[float]]:
    """``{checkpoint_idx: [raw episode_return, ...]}`` of one ``atari_episodes_ordered`` shard."""
    from rlu.codecs import example as ex
    from rlu.data.release.framing import RecordReader

    out: dict[int, list[float]] = defaultdict(list)
    reader = RecordReader(path, verify=verify)
    index = 0
    for batch in reader.batches():
        where = f"{os.fspath(path)} (records {index}..{index + len(batch) - 1})"
        try:
            cols = ex.decode_batch(batch)
        except FormatError as e:
            raise FormatError(f"{where}: {e}") from None
        index += len(batch)
        if not cols:
            continue
        ckpt = _scalar(cols, "checkpoint_idx", where).astype(np.int64)
        ret = _scalar(cols, "episode_return", where).astype(np.float64)
        for c, r in zip(ckpt.tolist(), ret.tolist(), strict=True):
            out[int(c)].append(float(r))
    return dict(out)


def run_of(path: str | os.PathLike) -> int:
    """The run number in a release file name (``run_3-00007-of-00050`` -> 3)."""
    m = _RUN_RE.search(os.path.basename(os.fspath(path)))
    if m is None:
        raise RluError(
            f"{path}: no run_N in the file name; release files are named run_N-IIIII-of-NNNNN"
        )
    return int(m.group(1))


def best_behaviour_from_release(
    paths: Sequence[str | os.PathLike], verify: bool = True
) -> dict[str, Any]:
    """One game's reference from its ``atari_episodes_ordered`` files (any runs, any shards).

    Returns ``{"mean": ..., "runs": {run: {"checkpoint", "mean", "episodes"}}, "episodes"}``:
    per run, the checkpoint with the highest mean raw episode return; ``mean`` averages those
    over the runs.
    """
    if not paths:
        raise RluError("no release files given; pass atari_episodes_ordered shards or --src ROOT")
    per_run: dict[int, dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
    for p in paths:
        run = run_of(p)
        for ckpt, returns in checkpoint_returns(p, verify=verify).items():
            per_run[run][ckpt].extend(returns)
    if not any(per_run.values()):
        raise RluError(f"the {len(paths)} files hold no episodes; are they atari_episodes_ordered?")
    return best_of_runs(per_run)


def best_of_runs(per_run: Mapping[int, Mapping[int, Sequence[float]]]) -> dict[str, Any]:
    """``{run: {checkpoint: [raw returns]}}`` -> the reference record (see the module doc)."""
    runs: dict[str, dict[str, Any]] = {}
    for run, by_ckpt in sorted(per_run.items()):
        means = {c: float(np.mean(r)) for c, r in by_ckpt.items() if r}
        if not means:
            continue
        best = max(means, key=lambda c: (means[c], -c))  # ties: the earlier checkpoint
        runs[str(run)] = {
            "checkpoint": best,
            "mean": means[best],
            "episodes": len(by_ckpt[best]),
            "checkpoints": len(means),
        }
    if not runs:
        raise RluError("no episodes to find a best checkpoint in")
    return {
        "mean": float(np.mean([r["mean"] for r in runs.values()])),
        "runs": runs,
        "episodes": int(sum(len(v) for by in per_run.values() for v in by.values())),
    }


def write(path: str | os.PathLike, doc: Mapping[str, Any]) -> None:
    """Write a reference file atomically (a crash leaves the old file or none)."""
    write_json(path, doc, indent=1)


# --- small denominators ---------------------------------------------------------------------
def small_denominator(
    random_mean: float, random_std: float, best: float, k: float = SPREAD_K
) -> bool:
    """Whether ``best - random_mean`` is under ``k`` random-return standard deviations (always
    when it is not positive: the normalisation is then meaningless)."""
    denom = float(best) - float(random_mean)
    return denom <= 0.0 or denom < k * float(random_std)


def denominator_check(
    random_mean: float,
    random_std: float,
    random_episodes: int,
    best: float,
    best_runs: Sequence[float] = (),
    k: float = SPREAD_K,
) -> dict[str, Any]:
    """The numbers behind a game's flag.

    ``separation``: ``(best - random) / random_std`` (inf for a random score without spread);
    ``reference_se``: the standard error the two references put on every normalised score, in
    normalised points, ``100 * sqrt(random_std**2 / random_episodes + sd(best_runs)**2 /
    len(best_runs)) / |best - random|`` (the runs' term only with two runs or more);
    ``flagged``: ``small_denominator``.
    """
    denom = float(best) - float(random_mean)
    var = float(random_std) ** 2 / max(int(random_episodes), 1)
    runs = np.asarray(best_runs, np.float64)
    if runs.size > 1:
        var += float(np.var(runs, ddof=1)) / runs.size
    return {
        "denominator": denom,
        "random_std": float(random_std),
        "separation": denom / float(random_std) if random_std > 0 else float("inf"),
        "reference_se": 100.0 * float(np.sqrt(var)) / abs(denom) if denom else float("inf"),
        "flagged": small_denominator(random_mean, random_std, best, k),
        "rule": f"best - random < {k:g} x the random returns' standard deviation",
    }


def denominator_flags(
    refs: Mapping[str, Mapping[str, float] | None],
    random_std: Mapping[str, float],
    k: float = SPREAD_K,
) -> dict[str, bool]:
    """``{task: flagged}`` for references ``{task: {"random", "best_behaviour"}}`` (the report's
    ``reference_scores``) and each game's random-return standard deviation; a game without a
    reference or a spread is left out."""
    return {
        task: small_denominator(r["random"], random_std[task], r["best_behaviour"], k)
        for task, r in refs.items()
        if r is not None and task in random_std
    }


def random_spread(path: str | os.PathLike | None = None) -> dict[str, float]:
    """``{task: standard deviation of random-play returns}`` from the random-scores file (the
    shipped one by default): the spread belongs to the game and env, so it serves any
    reference."""
    from rlu.envs.scores import load as load_random

    return {k: float(e["std"]) for k, e in load_random(path)["scores"].items() if "std" in e}


# --- the paper's table, normalised ----------------------------------------------------------
def paper_medians(
    paper: Mapping[str, Mapping[str, Mapping[str, float]]],
    random: Mapping[str, float],
    best: Mapping[str, float],
    online: Sequence[str],
    offline: Sequence[str],
) -> dict[str, dict[str, float]]:
    """Per agent, the median normalised score of the paper's per-game table (``{game: {agent:
    {"mean"}}}``, raw scores) over the ``online`` and over the ``offline`` selection games;
    ``random`` and ``best`` are keyed by game name. Every game of both lists must be in all
    three tables."""
    agents = sorted({a for g in (*online, *offline) for a in paper[g]})
    out: dict[str, dict[str, float]] = {}
    for agent in agents:
        row = {}
        for split, games in (("online", online), ("offline", offline)):
            norm = [
                100.0 * (paper[g][agent]["mean"] - random[g]) / (best[g] - random[g])
                for g in games
                if agent in paper[g]
            ]
            row[split] = float(np.median(norm))
        out[agent] = row
    return out
