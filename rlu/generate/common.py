"""What the three recipes share: seeds, success rule, selection, work folder, runs, merge,
progress, provenance.

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

Seeds: every random stream of a generation is one of ``rlu.seeds.seed_stream`` under the
command's ``--seed``, keyed by what it is for (``run_seed``, ``run_rng``, ``stream_rng``): one
subtree per run, so no two streams coincide whatever the counts of runs, episodes or chunks.

The work folder ``.<out>.generate`` beside ``out`` holds ``settings.json`` and each run's parts
and state; one generation at a time owns it (:func:`claim_work`: a second one into the same
``--out`` fails with "in use by PID N"), and what it holds is read back checked.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rlu.data import DatasetWriter, open_dataset
from rlu.domains import DOMAINS
from rlu.files import AnyJSON, MapOf, read_json, write_json
from rlu.generate.config import GenerateConfig
from rlu.generate.recorder import schema_for
from rlu.seeds import derive_seed, seed_stream
from rlu.segments import Segment
from rlu.tasks import TaskSpec
from rlu.types import RluError

CONTROL_SUCCESS_RETURN = 800.0

# --- seeds ----------------------------------------------------------------------------------
RUN, SELECTION, ROLLOUT = 0, 1, 2
"""The top-level streams under ``--seed``: the runs, the selection, RWRL's roll-outs."""
AGENT, ACTOR, EPISODE, ENV, POLICY = range(5)
"""A run's streams: the agent's initialisation, the actor's exploration, each episode's reset,
the env, each chunk's user policy."""


def run_seed(seed: int, run: int, stream: int, *key: int) -> int:
    """The int seed of stream ``stream`` (and ``key``, e.g. the episode) of run ``run``."""
    return derive_seed(seed, RUN, run, stream, *key)


def run_rng(seed: int, run: int, stream: int) -> np.random.Generator:
    return np.random.default_rng(seed_stream(seed, RUN, run, stream))


def stream_rng(seed: int, *key: int) -> np.random.Generator:
    return np.random.default_rng(seed_stream(seed, *key))


def success_rule(task: TaskSpec) -> str:
    """What counts as a successful episode of ``task`` when generation keeps successes, in words
    (the control suite: a return of at least 80% of 1000)."""
    success = DOMAINS[task.domain].success
    if success == "none":
        return "none: Atari keeps every recorded episode (the paper keeps DQN's replay)"
    if success == "time_limit":
        return "the episode reached its time limit (the walker did not fall or fail: not terminal)"
    return f"episode_return >= {CONTROL_SUCCESS_RETURN:g} (80% of the maximum 1000)"


def is_success(task: TaskSpec, returns: np.ndarray, terminal: np.ndarray) -> np.ndarray:
    """``terminal``: whether each episode ended in a terminal state (not a time limit)."""
    success = DOMAINS[task.domain].success
    if success == "none":
        return np.zeros(returns.shape, bool)
    if success == "time_limit":
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
    if DOMAINS[task.domain].success == "none":
        return None
    return int(task.episodes[""]) if "" in task.episodes else None


def versions(task: TaskSpec) -> dict[str, str]:
    """Versions of the packages the bytes depend on (recorded in the provenance)."""
    from importlib import metadata

    sim = list(DOMAINS[task.domain].sim_packages)
    out = {}
    for n in ["numpy", "torch", *sim]:
        try:
            out[n] = metadata.version(n)
        except metadata.PackageNotFoundError:
            pass
    return out


def work_folder(out: Path) -> Path:
    """Where a generation into ``out`` keeps its work until the dataset is written."""
    return out.parent / f".{out.name}.generate"


@contextlib.contextmanager
def claim_work(out: Path) -> Iterator[Path]:
    """Own the work folder of the generation into ``out`` while the block runs: a second
    generation into the same ``out`` fails at once with "in use by PID N" (a killed one's
    claim ends with it: :class:`rlu.locks.OutputLock`)."""
    from rlu.locks import OutputLock

    work = work_folder(out)
    with OutputLock(work, f"work folder of the generation into {out}"):
        yield work


def open_work(work: Path, settings: dict[str, Any], resume_command: str) -> None:
    """Create the work folder with ``settings.json``, or check that the interrupted generation
    there used the same settings (a resumed run must give the bytes of an uninterrupted one)."""
    path = work / "settings.json"
    if path.exists():
        fix = f"remove {work} to start the generation afresh"
        before = read_json(path, MapOf(AnyJSON()), fix)
        if before != settings:
            diff = sorted(
                k for k in settings.keys() | before.keys() if before.get(k) != settings.get(k)
            )
            raise RluError(
                f"{work} holds an interrupted generation with other settings ({', '.join(diff)}); "
                f"re-run its command ({resume_command}) to resume it, or remove {work}"
            )
        return
    work.mkdir(parents=True, exist_ok=True)
    write_json(path, settings, indent=1)


def play_runs(
    config: GenerateConfig,
    play: Callable[..., None],
    jobs: Sequence[tuple[Any, ...]],
    bar: Progress,
) -> None:
    """``play(*job)`` for every run's job on ``config.backend`` (the one runner,
    ``rlu.workers.run_jobs``): each run is a function of its seeds alone, so the bytes do not
    depend on the backend or the number of workers. A run reports its episodes with
    :func:`report_episode`; they reach ``bar``."""
    from rlu.devices import check_ray_gpus
    from rlu.workers import run_jobs

    def ray_check(ray: Any) -> None:
        check_ray_gpus(ray, config.backend.gpus_per_job, config.device)

    run_jobs(
        play,
        jobs,
        config.backend,
        on_result=lambda i, r: None,
        on_message=lambda m: bar.report(*m),
        ray_check=ray_check,
    )


def report_episode(run: int, episode: int, seg: Segment) -> None:
    """From inside a run: its ``episode``-th episode ended (the parent's progress bar)."""
    from rlu.workers import send

    send((run, episode, float(seg.metadata["episode_return"])))


def merge_runs(
    task: TaskSpec,
    work: Path,
    out: Path,
    settings: dict[str, Any],
    command: str,
    policies: str | None = None,
) -> Path:
    """Select episodes from every run's parts under ``work`` and write the final dataset to
    ``out`` (``settings``: the generation's, with its runs, seed and target episodes). The
    provenance keeps every recorded episode's return and length per run (``runs``): the runs'
    learning curves, of which the dataset keeps a sub-sample (``rlu.generate.curves``).
    ``policies`` (the weights' dtype; None: the recipe keeps none): attach the behaviour policy
    of every (run, checkpoint) the kept episodes name, from ``work/run_*/policies/``."""
    parts, curves = [], []
    for r in range(settings["runs"]):
        run_parts = sorted((work / f"run_{r:03d}").glob("part_*"))
        mine = [open_dataset(p) for p in run_parts if (p / "manifest.json").exists()]
        parts += mine
        curve = [round(float(x), 3) for p in mine for x in np.asarray(p.metadata("episode_return"))]
        lengths = [int(n) - 1 for p in mine for n in np.asarray(p.length)]
        curves.append({"run": r, "episode_return": curve, "episode_steps": lengths})
    returns = np.concatenate([np.asarray(p.metadata("episode_return")) for p in parts])
    terminal = np.concatenate(
        [np.asarray(p.column("is_terminal"))[p.start + p.length - 1] for p in parts]
    )
    where = [(i, j) for i, p in enumerate(parts) for j in range(len(p))]
    rng = stream_rng(settings["seed"], SELECTION)
    target = settings["target_episodes"]
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
    """Generation's progress on the one display (``rlu.progress``): episodes played over every
    run, with the latest run, episode and return after the counts."""

    def __init__(self, total: int, label: str, enabled: bool = True):
        from rlu.progress import Progress as Display

        self.latest: dict[int, int] = {}  # run -> its last episode number (1-based)
        self.done = 0
        # a budget in env steps has no episode count: total 0 shows counts without a bar
        self.display = Display(total or None, label, "episodes", quiet=not enabled)

    def update(self, run: int, episode: int, seg: Segment) -> None:
        self.report(run, episode, float(seg.metadata["episode_return"]))

    def report(self, run: int, episode: int, episode_return: float) -> None:
        # episodes played, counted from each run's episode number: a resumed run's first report
        # counts the episodes it played before the interruption too
        self.latest[run] = episode
        self.done = sum(self.latest.values())
        self.display.set_postfix(run=run, episode=episode, ret=f"{episode_return:.1f}")
        self.display.update_to(self.done)

    def close(self) -> None:
        self.display.close()
