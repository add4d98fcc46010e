"""The paper's data-generation recipe at three scales (SPEC §4).

``generate(task, out, scale, runs, seed)``:

1. plays ``runs`` independent online training runs of the behaviour agent (D4PG for the control
   suite, DQN with sticky actions for Atari; ``rlu.generate.online``) and records every episode
   with its run, seed, checkpoint and episode index;
2. keeps only a third of the *successful* episodes (the paper: "we further reduce the number of
   successful episodes by 2/3"), chosen uniformly at random;
3. sub-samples the rest uniformly to the task's target episode count (the paper's count, e.g.
   40 for cartpole swingup), keeping the order of recording;
4. writes one dataset whose manifest holds the command, the seed, the resolved settings, the
   behaviour agent's config, the success rule and the selection counts (no clock time, so the same
   seed gives the same bytes).

Success, per domain (``success_rule``):

- control suite: the episode return is at least 800, i.e. 80 % of the maximum 1000 (every task
  rewards at most 1 per step over 1000 steps); D4PG's converged returns on the tasks the paper
  calls solved lie above it;
- Atari: no episode counts as successful: the paper keeps DQN's whole replay (no reduction).

Resumption: the work goes to ``.<out>.generate/`` next to ``out``: one store part per chunk of
episodes per run, written atomically, and a per-run ``state.pt`` (agent, replay, random
generator) saved after each part. Re-running the same command resumes every unfinished run
from its last saved chunk and gives the bytes of an uninterrupted run; the work folder is
removed once the dataset is written. Settings that differ from the interrupted run's are an
error.

RWRL (fixed sub-optimal snapshots rolled out under challenge none and easy) is in
``rlu.generate.rwrl``; it writes one dataset per ``{challenge}_{size}`` under ``out``.
Locomotion records a policy the user supplies (``--policy module:factory``,
``rlu.generate.policy``); its success: the episode reached its time limit.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rlu.data import DatasetWriter, open_dataset
from rlu.data.episode import Segment
from rlu.devices import check_gpus_per_run, check_ray_gpus, ray_options
from rlu.generate.online import OnlineConfig, run_online
from rlu.generate.recorder import schema_for
from rlu.tasks import TaskSpec, get_task
from rlu.types import RluError

SCALES = ("tiny", "small", "paper")
CONTROL_SUCCESS_RETURN = 800.0

_TINY_D4PG = {"policy_layers": (32, 32), "critic_layers": (32, 32), "batch_size": 32}
_TINY_DQN = {"atari.channels": (8, 16, 16), "atari.hidden_size": 32, "atari.batch_size": 16}


@dataclass(frozen=True)
class Scale:
    """One scale of the recipe for one domain."""

    runs: int
    """Independent training runs (the paper: 3 for the control suite, 5 for Atari)."""
    online: OnlineConfig
    """Each run's behaviour agent and budget."""
    target_episodes: int | None
    """Episodes kept after selection; None: the paper's count for the task."""


def _scales(domain: str) -> dict[str, Scale]:
    if domain == "control_suite":
        return {
            # seconds: for tests and smoke runs; tiny networks, learning barely starts
            "tiny": Scale(2, OnlineConfig("d4pg", episodes=2, agent_overrides=_TINY_D4PG,
                                          replay_capacity=5_000, min_replay=500, update_every=16,
                                          checkpoint_steps=1_000, chunk_episodes=1), None),
            # minutes on a laptop: the small D4PG preset, 3 runs of 30 episodes (90K steps)
            "small": Scale(3, OnlineConfig("d4pg", episodes=30, replay_capacity=100_000,
                                           min_replay=2_000, update_every=8,
                                           checkpoint_steps=10_000, chunk_episodes=5), None),
            # the paper's: Acme's D4PG, 3 runs of 1M steps each
            "paper": Scale(3, OnlineConfig("d4pg", episodes=1_000, preset="paper",
                                           replay_capacity=1_000_000, min_replay=10_000,
                                           update_every=8, checkpoint_steps=100_000,
                                           chunk_episodes=20), None),
        }  # fmt: skip
    if domain == "atari":
        return {
            "tiny": Scale(1, OnlineConfig("dqn", episodes=2, agent_overrides=_TINY_DQN,
                                          replay_capacity=2_000, min_replay=50, update_every=4,
                                          epsilon_decay_steps=1_000, checkpoint_steps=100,
                                          chunk_episodes=1,
                                          env_settings={"max_episode_steps": 100}), None),
            "small": Scale(2, OnlineConfig("dqn", episodes=10_000, env_steps=50_000,
                                           replay_capacity=50_000, min_replay=5_000,
                                           update_every=4, epsilon_decay_steps=25_000,
                                           checkpoint_steps=10_000, chunk_episodes=5), None),
            # Dopamine's DQN: 50M agent steps per run, 1M replay, 1M-step checkpoints
            "paper": Scale(5, OnlineConfig("dqn", episodes=10**9, env_steps=50_000_000,
                                           preset="paper", replay_capacity=1_000_000,
                                           min_replay=20_000, update_every=4,
                                           epsilon_decay_steps=250_000,
                                           checkpoint_steps=1_000_000, chunk_episodes=50), None),
        }  # fmt: skip
    raise RluError(
        f"rlu generate supports the control_suite, atari and rwrl domains; {domain!r} is not "
        "implemented yet (locomotion: record your own policy with "
        "rlu.generate.recorder.record_policy)"
    )


def get_scale(task: TaskSpec, scale: str) -> Scale:
    scales = _scales(task.domain)
    if scale not in scales:
        raise RluError(f"unknown --scale {scale!r}; use one of {', '.join(SCALES)}")
    return scales[scale]


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


def command_line(task_id: str, scale: str, runs: int, seed: int) -> str:
    """The command recorded in the manifest (``--out`` left out: it does not change the data)."""
    return f"rlu generate {task_id} --scale {scale} --seeds {runs} --seed {seed}"


def _versions(task: TaskSpec) -> dict[str, str]:
    from importlib import metadata

    sim = ["ale-py"] if task.domain == "atari" else ["dm-control", "mujoco"]
    names = ["numpy", "torch", *sim]
    out = {}
    for n in names:
        try:
            out[n] = metadata.version(n)
        except metadata.PackageNotFoundError:
            pass
    return out


class Progress:
    """A one-line progress bar on stderr (one line per run when stderr is not a terminal)."""

    def __init__(self, total: int, label: str, enabled: bool = True):
        self.total, self.label, self.enabled = total, label, enabled
        self.done, self.t0 = 0, time.perf_counter()
        self.tty = sys.stderr.isatty()

    def update(self, run: int, episode: int, seg: Segment) -> None:
        self.done += 1
        if not self.enabled:
            return
        frac = self.done / self.total if self.total else 0.0  # 0: a budget in env steps
        bar = "#" * int(30 * min(1.0, frac))
        el = time.perf_counter() - self.t0
        msg = (
            f"{self.label} [{bar:<30}] {self.done}/{self.total or '?'} episodes  run {run} "
            f"ep {episode} return {float(seg.metadata['episode_return']):8.1f}  {el:6.0f}s"
        )
        if self.tty:
            print("\r" + msg, end="", file=sys.stderr, flush=True)
        elif episode == 1 or self.done == self.total or self.done % 10 == 0:
            print(msg, file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.enabled and self.tty:
            print(file=sys.stderr)


def _part_path(work: Path, run: int, chunk: int) -> Path:
    return work / f"run_{run:03d}" / f"part_{chunk:05d}"


def _run_one(task_id: str, online: OnlineConfig, seed: int, run: int, work: str,
             on_chunk=None, on_episode=None, device: str = "cpu") -> None:  # fmt: skip
    task = get_task(task_id)
    schema = schema_for(task)

    def write_chunk(chunk: int, segs: list[Segment]) -> None:
        with DatasetWriter(_part_path(Path(work), run, chunk), schema, overwrite=True) as w:
            for s in segs:
                w.append(s)

    run_dir = Path(work) / f"run_{run:03d}"
    run_online(task, online, seed, run, run_dir, write_chunk, on_episode, on_chunk,
               device=device)  # fmt: skip


def generate(
    task_id: str,
    out: str | Path,
    scale: str = "small",
    runs: int | None = None,
    seed: int = 0,
    backend: str = "local",
    progress: bool = True,
    on_chunk: Callable[[int, int], None] | None = None,
    keep_work: bool = False,
    policy: str | None = None,
    device: str = "cpu",
    gpus_per_run: float = 0.0,
) -> Path:
    """Run the recipe (see the module docstring); returns the dataset's path. ``policy``
    ('module:factory', see ``rlu.generate.policy``) records a user policy instead of training
    the behaviour agent (required for locomotion). The behaviour agents learn on ``device``;
    on Ray each run asks for ``gpus_per_run`` GPUs (a fraction shares one)."""
    task = get_task(task_id)
    check_gpus_per_run(gpus_per_run)
    if gpus_per_run and backend != "ray":
        raise RluError("--gpus-per-run asks Ray for GPUs; use it with --backend ray")
    if policy is not None or task.domain == "locomotion":
        from rlu.generate.policy import generate_with_policy

        if policy is None:
            raise RluError(
                f"{task.id}: locomotion data comes from a policy you supply: pass --policy "
                "package.module:factory, factory(task_id, seed) -> policy(observation) -> action"
            )
        if scale not in SCALES or backend != "local":
            raise RluError(f"--policy runs with --backend local and --scale one of {SCALES}")
        return generate_with_policy(task, Path(out), scale, runs, seed, policy, progress,
                                    keep_work)  # fmt: skip
    if task.domain == "rwrl":
        from rlu.generate.rwrl import generate_rwrl

        if scale not in SCALES:
            raise RluError(f"unknown --scale {scale!r}; use one of {', '.join(SCALES)}")
        if backend != "local":
            raise RluError("rwrl generation runs with --backend local only")
        return generate_rwrl(task, Path(out), scale, runs, seed, progress, keep_work, device)
    sc = get_scale(task, scale)
    runs = sc.runs if runs is None else int(runs)
    if runs < 1:
        raise RluError(f"--seeds {runs}: give at least 1 run")
    out = Path(out)
    if (out / "manifest.json").exists():
        raise RluError(f"{out} already holds a dataset; choose another --out or remove it")
    target = sc.target_episodes if sc.target_episodes is not None else _paper_count(task)
    from rlu.agents import make_config

    agent_cfg = make_config(sc.online.agent, task.discrete, sc.online.preset,
                            **sc.online.agent_overrides)  # fmt: skip
    settings = {
        "task": task.id,
        "scale": scale,
        "runs": runs,
        "seed": int(seed),
        "online": sc.online.to_json(),
        "agent_config": dataclasses.asdict(agent_cfg),
        "target_episodes": target,
        "success_rule": success_rule(task),
    }
    settings = json.loads(json.dumps(settings))  # tuples -> lists, as read back
    work = out.parent / f".{out.name}.generate"
    cfg_path = work / "settings.json"
    if cfg_path.exists():
        before = json.loads(cfg_path.read_text())
        if before != settings:
            diff = sorted(k for k in settings if before.get(k) != settings.get(k))
            cmd = command_line(before["task"], before["scale"], before["runs"], before["seed"])
            raise RluError(
                f"{work} holds an interrupted generation with other settings ({', '.join(diff)}); "
                f"re-run its command ({cmd} --out {out}) to resume it, or remove {work}"
            )
    else:
        work.mkdir(parents=True, exist_ok=True)
        tmp = cfg_path.with_name(".settings.json.tmp")
        tmp.write_text(json.dumps(settings, indent=1, sort_keys=True))
        tmp.replace(cfg_path)

    bar = Progress(runs * sc.online.episodes if sc.online.env_steps is None else 0,
                   task.id, progress)  # fmt: skip
    if backend == "local":
        for r in range(runs):
            _run_one(task.id, sc.online, seed, r, str(work), on_chunk, bar.update, device)
    elif backend == "ray":
        _run_ray(task.id, sc.online, seed, runs, str(work), device, gpus_per_run)
    else:
        raise RluError(f"unknown --backend {backend!r}; use 'local' or 'ray'")
    bar.close()
    path = _merge(task, work, runs, settings, target, seed, out)
    if not keep_work:
        shutil.rmtree(work)
    return path


def _run_ray(task_id: str, online: OnlineConfig, seed: int, runs: int, work: str,
             device: str = "cpu", gpus_per_run: float = 0.0) -> None:  # fmt: skip
    try:
        import ray
    except ImportError as e:
        raise RluError(
            "--backend ray needs the 'distributed' extra: bash scripts/install.sh distributed"
        ) from e
    started = not ray.is_initialized()
    if started:
        ray.init(ignore_reinit_error=True, log_to_driver=False, include_dashboard=False)
    try:
        check_ray_gpus(ray, gpus_per_run, device)
        remote = ray.remote(**ray_options(gpus_per_run))(_run_one)
        # Runs share nothing but the work folder, which must be on a filesystem every node sees;
        # each run is a function of (seed, run) alone, so the bytes equal the local backend's.
        ray.get([remote.remote(task_id, online, seed, r, work, device=device)
                 for r in range(runs)])  # fmt: skip
    finally:
        if started:
            ray.shutdown()


def _paper_count(task: TaskSpec) -> int | None:
    if task.domain == "atari":
        return None
    return int(task.episodes[""]) if "" in task.episodes else None


def _merge(task, work: Path, runs: int, settings, target, seed: int, out: Path,
           command: str | None = None) -> Path:  # fmt: skip
    parts = []
    for r in range(runs):
        run_parts = sorted((work / f"run_{r:03d}").glob("part_*"))
        parts += [open_dataset(p) for p in run_parts if (p / "manifest.json").exists()]
    returns = np.concatenate([np.asarray(p.metadata("episode_return")) for p in parts])
    terminal = np.concatenate(
        [np.asarray(p.column("is_terminal"))[p.start + p.length - 1] for p in parts]
    )
    where = [(i, j) for i, p in enumerate(parts) for j in range(len(p))]
    rng = np.random.default_rng([seed, 3])
    keep, counts = select_episodes(is_success(task, returns, terminal), target, rng)
    provenance = {
        "generator": "rlu generate",
        "command": command or command_line(task.id, settings["scale"], runs, seed) + " --out DIR",
        "settings": settings,
        "selection": counts,
        "versions": _versions(task),
    }
    with DatasetWriter(out, schema_for(task), provenance=provenance) as w:
        for k in keep.tolist():
            i, j = where[k]
            w.append(parts[i].segment(j))
    return out


BUNDLED_TASK = "control_suite/cartpole_swingup"


def bundled_dataset(task_id: str = BUNDLED_TASK) -> Path:
    """The dataset shipped in the package (made by ``rlu generate``; its manifest holds the
    command and seed)."""
    from importlib import resources

    path = Path(str(resources.files("rlu"))) / "resources" / "datasets" / task_id
    if not (path / "manifest.json").exists():
        raise RluError(
            f"{path}: no bundled dataset for {task_id!r}; the package ships {BUNDLED_TASK} only "
            "(reinstall rlu if it is missing)"
        )
    return path
