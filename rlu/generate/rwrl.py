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
runs resume like ``rlu generate``; a finished dataset is skipped; snapshots are saved per run.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data import DatasetWriter, Schema
from rlu.generate.common import Progress, command_line, open_work, versions
from rlu.generate.online import derive_seed, make_behaviour_agent, run_online
from rlu.generate.recorder import EpisodeRecorder, episode_id
from rlu.generate.scales import get_scale
from rlu.tasks import RWRL_SIZES, TaskSpec, rwrl_observation_spec

SNAPSHOT_FRACTION = 0.75
CHALLENGES = ("none", "easy")
SIZE_FRACTION = {"tiny": None, "laptop": 0.1, "paper": 1.0}
TINY_EPISODES = {"small": 1, "medium": 1, "large": 2}


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


def generate_rwrl(task: TaskSpec, out: Path, scale: str, runs: int | None, seed: int,
                  progress: bool = True, keep_work: bool = False,
                  device: str = "cpu") -> Path:  # fmt: skip
    import torch

    from rlu.envs import make_env

    # the control suite's D4PG settings at this scale: the same agent, the same budget
    sc = get_scale(task, scale)
    runs, online = sc.runs if runs is None else int(runs), sc.online
    out.mkdir(parents=True, exist_ok=True)
    work = out / ".work"
    settings = {"task": task.id, "scale": scale, "runs": runs, "seed": seed,
                "online": online.to_json(), "snapshot_fraction": SNAPSHOT_FRACTION}  # fmt: skip
    settings = json.loads(json.dumps(settings))
    command = command_line(task.id, scale, runs, seed)
    open_work(work, settings, f"{command} --out {out}")

    # 1. training runs, keeping each chunk's policy and mean return
    snapshots = []
    bar = Progress(runs * online.episodes, task.id + " (training)", progress)
    for r in range(runs):
        run_dir = work / f"run_{r:03d}"
        snap_path = run_dir / "snapshot.pt"
        if not snap_path.exists():
            # chunk -> (mean return, agent state), saved per chunk so a resumed run sees them all
            hist_path = run_dir / "snapshots.pt"
            history: dict[int, Any] = {}
            if hist_path.exists():
                history = torch.load(hist_path, weights_only=True, map_location="cpu")

            def keep(chunk: int, agent: Any, segs: list, history=history, path=hist_path) -> None:
                ret = float(np.mean([s.metadata["episode_return"] for s in segs]))
                history[chunk] = (ret, agent.state_dict())
                tmp = path.with_name(".snapshots.pt.tmp")
                torch.save(history, tmp)
                os.replace(tmp, path)

            # the run's own recorded episodes are not part of the RWRL datasets
            run_online(task, online, seed, r, run_dir, lambda c, s: None, bar.update,
                       on_snapshot=keep, device=device)  # fmt: skip
            chunks = sorted(history)
            i, converged = _choose([history[c][0] for c in chunks])
            snap = {"chunk": chunks[i], "return": history[chunks[i]][0], "converged": converged,
                    "agent": history[chunks[i]][1]}  # fmt: skip
            tmp = snap_path.with_name(".snapshot.pt.tmp")
            torch.save(snap, tmp)
            os.replace(tmp, snap_path)
        snapshots.append(torch.load(snap_path, weights_only=True, map_location="cpu"))
    bar.close()
    agents = []
    for r, snap in enumerate(snapshots):
        agent = make_behaviour_agent(task, online, derive_seed(seed, r), device)
        agent.load_state_dict(snap["agent"])
        agents.append(agent)

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
                n = episodes_for(task, challenge, size, scale)
                env = make_env(task.id, seed=seed, challenge=challenge)
                rec = EpisodeRecorder(task, observation_spec=obs_spec)
                rng = np.random.default_rng([seed, 4, CHALLENGES.index(challenge),
                                             list(RWRL_SIZES).index(size)])  # fmt: skip
                keys = list(task.observation_spec)
                prov = {
                    "generator": "rlu generate (rwrl snapshots)",
                    "command": command + " --out DIR",
                    "settings": settings,
                    "challenge": challenge,
                    "size": size,
                    "snapshots": [{k: v for k, v in s.items() if k != "agent"} for s in snapshots],
                    "versions": versions(task),
                }
                with DatasetWriter(dest, schema, provenance=prov, overwrite=True) as w:
                    for e in range(n):
                        r = e % runs
                        meta = {"run": r, "seed": seed, "checkpoint": snapshots[r]["chunk"],
                                "episode_index": e, "episode_id": episode_id(r, e)}  # fmt: skip
                        obs, _ = env.reset(seed=derive_seed(seed, 5, e))
                        rec.begin(obs)
                        while True:
                            o = {k: obs[k][None] for k in keys}
                            if online.sigma is None:  # DMPO: a sample of its own Gaussian
                                a = agents[r].act(o, greedy=False)[0]
                            else:
                                a = agents[r].act(o)[0]
                                noise = rng.standard_normal(a.shape).astype(np.float32)
                                a = a + online.sigma * noise
                            a = np.clip(a, -1.0, 1.0)
                            obs, rew, term, trunc, info = env.step(a)
                            seg = rec.step(a, rew, obs, term, trunc, info, meta)
                            if seg is not None:
                                break
                        w.append(seg)
                env.close()
    finally:
        torch.set_num_threads(threads)
    if not keep_work:
        shutil.rmtree(work)
    summary = {"task": task.id, "datasets": sorted(p.name for p in out.iterdir() if p.is_dir()),
               "settings": settings}  # fmt: skip
    (out / "rwrl.json").write_text(json.dumps(summary, indent=1, sort_keys=True))
    return out


__all__ = ["generate_rwrl", "SNAPSHOT_FRACTION"]
