"""RWRL datasets: fixed sub-optimal behaviour snapshots rolled out with and without challenges.

The paper's RWRL data came from "fixed sub-optimal snapshots (≈75 % of converged return,
3 seeds)" of a distributional MPO agent. Here, per run (seed), the scale's behaviour agent
(DMPO at the ``paper`` scale, as the paper; D4PG at ``laptop`` and ``tiny``, the control suite's
laptop runs) trains on the task without challenge exactly as ``rlu.generate.online`` does; after
every chunk of episodes the policy is kept with the chunk's mean return. The run's *converged
return* is the best chunk mean; its snapshot is the first one whose chunk mean reaches
``SNAPSHOT_FRACTION`` (75 %) of it. Each dataset (``{challenge}/{size}``: ``none`` and ``easy``,
sizes small / medium / large) is then rolled out from the runs' snapshots in turn (episode i from
run i mod runs), acting as the behaviour did (D4PG: the snapshot's policy plus the noise
``sigma``; DMPO: a sample of its Gaussian), and written to ``OUT/{challenge}_{size}``.

Under the easy challenge the env adds ten ``dummy-i`` observation keys (as released); the
snapshot policy sees only the task's own keys. Episode counts: the paper's (TaskSpec.episodes,
e.g. cartpole 100 / 200 / 500) times the scale's ``size_fraction``. Resumption: the training
runs resume like ``rlu generate`` and play through the same runner (local processes or Ray); a
finished dataset is skipped; snapshots are saved per run (``rlu.training.checkpoints``) and read
back checked. The roll-outs draw from the ``ROLLOUT`` streams of ``--seed``: the env's resets are
shared by every dataset (episode e starts alike in each), the noise is each dataset's own.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data import DatasetWriter, Schema
from rlu.files import write_atomic
from rlu.generate.common import (
    AGENT,
    ROLLOUT,
    Progress,
    open_work,
    play_runs,
    report_episode,
    run_seed,
    stream_rng,
    versions,
)
from rlu.generate.config import GenerateConfig
from rlu.generate.online import OnlineConfig, RunHooks, make_behaviour_agent, run_online
from rlu.generate.recorder import EpisodeRecorder, episode_id
from rlu.generate.scales import get_scale
from rlu.seeds import derive_seed
from rlu.tasks import RWRL_SIZES, TaskSpec, rwrl_observation_spec
from rlu.types import FormatError

SNAPSHOT_FRACTION = 0.75
"""An RWRL run's snapshot is its first policy whose chunk mean reaches this fraction of the run's
converged return (the paper's "≈75 % of converged return")."""
CHALLENGES = ("none", "easy")
SIZE_FRACTION = {"tiny": None, "laptop": 0.1, "paper": 1.0}
TINY_EPISODES = {"small": 1, "medium": 1, "large": 2}
SUMMARY = "rwrl.json"
"""The file that marks a finished RWRL generation's folder (its datasets and settings)."""


def episodes_for(task: TaskSpec, challenge: str, size: str, scale: str) -> int:
    frac = SIZE_FRACTION[scale]
    if frac is None:
        return TINY_EPISODES[size]
    # the easy challenge was released at the large size only; other sizes keep none's counts
    return max(1, round(task.episodes[f"none/{size}"] * frac))


def _choose(returns: list[float]) -> tuple[int, float]:
    r = np.asarray(returns, np.float64)
    converged = float(r.max())
    hit = np.flatnonzero(r >= SNAPSHOT_FRACTION * converged)
    return int(hit[0]), converged


def _damaged(path: Path, what: str, run_dir: Path) -> FormatError:
    return FormatError(
        f"{path}: {what}, not a snapshot rlu generate saved; remove {run_dir} to train run "
        f"{run_dir.name} again"
    )


def _load_history(path: Path, run_dir: Path) -> dict[int, Any]:
    from rlu.training.checkpoints import load_state

    # the keys are the file's, of any type, until each is checked a chunk index below
    history: dict[Any, Any] = load_state(path, fix=f"remove {run_dir} to train this run again")
    for chunk, entry in history.items():
        if isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 0:
            raise _damaged(path, f"key {chunk!r} is not a chunk index", run_dir)
        if not (
            isinstance(entry, tuple | list)
            and len(entry) == 2
            and isinstance(entry[0], float)
            and isinstance(entry[1], dict)
        ):
            raise _damaged(
                path, f"chunk {chunk}'s entry is not (mean return, agent state)", run_dir
            )
    return history


def train_snapshot(config: GenerateConfig, online: OnlineConfig, run: int, work: Path) -> None:
    """One run's job: train it (resuming), keeping each chunk's policy and mean return, then
    save its snapshot (``run_RRR/snapshot.pt``)."""
    from rlu.training.checkpoints import save_state

    run_dir = work / f"run_{run:03d}"
    if (run_dir / "snapshot.pt").exists():
        return
    # chunk -> (mean return, agent state), saved per chunk so a resumed run sees them all
    hist_path = run_dir / "snapshots.pt"
    history = _load_history(hist_path, run_dir) if hist_path.exists() else {}

    def keep(chunk: int, agent: Any, segs: list) -> None:
        ret = float(np.mean([s.metadata["episode_return"] for s in segs]))
        history[chunk] = (ret, agent.state_dict())
        save_state(hist_path, history)

    # the run's own recorded episodes are not part of the RWRL datasets
    hooks = RunHooks(lambda c, s: None, report_episode, on_snapshot=keep)
    run_online(config, online, run, run_dir, hooks)
    chunks = sorted(history)
    i, converged = _choose([history[c][0] for c in chunks])
    snap = {
        "chunk": chunks[i],
        "return": history[chunks[i]][0],
        "converged": converged,
        "agent": history[chunks[i]][1],
    }
    save_state(run_dir / "snapshot.pt", snap)


def _load_snapshot(path: Path, agent: Any) -> dict[str, Any]:
    from rlu.training.checkpoints import load_state

    run_dir = path.parent
    snap = load_state(path, ("chunk", "return", "converged", "agent"), f"remove {run_dir}")
    if isinstance(snap["chunk"], bool) or not isinstance(snap["chunk"], int):
        raise _damaged(path, f"entry 'chunk' is {snap['chunk']!r}", run_dir)
    if not all(isinstance(snap[k], float) for k in ("return", "converged")):
        raise _damaged(path, "its returns are not numbers", run_dir)
    try:
        agent.load_state_dict(snap["agent"])
    except (RuntimeError, KeyError, ValueError, TypeError, AttributeError, IndexError) as e:
        why = str(e).splitlines()[0][:200] if str(e) else type(e).__name__
        raise _damaged(
            path, f"its agent state does not fit the behaviour agent ({why})", run_dir
        ) from None
    return {k: v for k, v in snap.items() if k != "agent"}


def _train_snapshots(
    config: GenerateConfig, task: TaskSpec, online: OnlineConfig, runs: int, work: Path
) -> tuple[list[Any], list[dict[str, Any]]]:
    """Play the training runs (each keeping its chunks' policies and mean returns), then
    (each run's behaviour agent, its snapshot's record) with the snapshot loaded."""
    bar = Progress(runs * online.episodes, task.id + " (training)", config.progress)
    play_runs(config, train_snapshot, [(config, online, r, work) for r in range(runs)], bar)
    bar.close()
    agents, snapshots = [], []
    for r in range(runs):
        agent = make_behaviour_agent(task, online, run_seed(config.seed, r, AGENT), config.device)
        snapshots.append(_load_snapshot(work / f"run_{r:03d}" / "snapshot.pt", agent))
        agents.append(agent)
    return agents, snapshots


def _episode(
    env: Any,
    rec: EpisodeRecorder,
    agent: Any,
    sigma: float | None,
    rng: np.random.Generator,
    reset: int,
    meta: Mapping[str, Any],
) -> Any:
    """One episode of a snapshot, from the env reset with seed ``reset``, acting as the
    behaviour did (``sigma``: D4PG's noise; None: a sample of DMPO's own Gaussian) on the
    task's own observation keys; its recorded segment."""
    spec = rec.task.observation_spec
    assert isinstance(spec, Mapping)  # RWRL observes a dict
    keys = list(spec)  # the task's own: the easy challenge's dummy keys are left out
    obs, _ = env.reset(seed=reset)
    rec.begin(obs)
    while True:
        o = {k: obs[k][None] for k in keys}
        if sigma is None:
            a = agent.act(o, greedy=False)[0]
        else:
            a = agent.act(o)[0]
            a = a + sigma * rng.standard_normal(a.shape).astype(np.float32)
        a = np.clip(a, -1.0, 1.0)
        obs, rew, term, trunc, info = env.step(a)
        seg = rec.step(a, rew, obs, term, trunc, info, meta)
        if seg is not None:
            return seg


def generate_rwrl(config: GenerateConfig, task: TaskSpec, out: Path, work: Path) -> Path:
    """Train the runs, snapshot them and roll out every dataset into ``out`` (see the module
    docstring), working in the claimed ``work`` folder; returns ``out``."""
    import torch

    from rlu.envs import make_env

    # the control suite's D4PG settings at this scale: the same agent, the same budget
    sc = get_scale(task, config.scale)
    runs, online, seed = sc.runs if config.runs is None else config.runs, sc.online, config.seed
    settings = {
        "task": task.id,
        "scale": config.scale,
        "runs": runs,
        "seed": seed,
        "online": online.to_json(),
        "snapshot_fraction": SNAPSHOT_FRACTION,
    }
    settings = json.loads(json.dumps(settings))
    command = config.command(runs)
    open_work(work, settings, f"{command} --out {out}")
    out.mkdir(parents=True, exist_ok=True)

    agents, snapshots = _train_snapshots(config, task, online, runs, work)

    # 2. roll out every dataset from the snapshots
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for challenge in CHALLENGES:
            obs_spec = rwrl_observation_spec(task, challenge)
            schema = Schema.for_task(task, observation=obs_spec)
            for size in RWRL_SIZES:
                dest = out / f"{challenge}_{size}"
                if (dest / "manifest.json").exists():
                    continue
                n = episodes_for(task, challenge, size, scale=config.scale)
                env = make_env(task.id, seed=derive_seed(seed, ROLLOUT, 0), challenge=challenge)
                rec = EpisodeRecorder(task, observation_spec=obs_spec)
                rng = stream_rng(
                    seed, ROLLOUT, 2, CHALLENGES.index(challenge), list(RWRL_SIZES).index(size)
                )
                prov = {
                    "generator": "rlu generate (rwrl snapshots)",
                    "command": command + " --out DIR",
                    "settings": settings,
                    "challenge": challenge,
                    "size": size,
                    "snapshots": snapshots,
                    "versions": versions(task),
                }
                with DatasetWriter(dest, schema, provenance=prov, overwrite=True) as w:
                    for e in range(n):
                        r = e % runs
                        meta = {
                            "run": r,
                            "seed": seed,
                            "checkpoint": snapshots[r]["chunk"],
                            "episode_index": e,
                            "episode_id": episode_id(r, e),
                        }
                        reset = derive_seed(seed, ROLLOUT, 1, e)
                        w.append(_episode(env, rec, agents[r], online.sigma, rng, reset, meta))
                env.close()
    finally:
        torch.set_num_threads(threads)
    summary = {
        "task": task.id,
        "datasets": sorted(p.name for p in out.iterdir() if p.is_dir()),
        "settings": settings,
    }
    write_atomic(out / SUMMARY, json.dumps(summary, indent=1, sort_keys=True))
    if not config.keep_work:
        shutil.rmtree(work)
    return out


__all__ = ["SNAPSHOT_FRACTION", "generate_rwrl"]
