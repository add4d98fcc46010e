"""``rlu envs random-scores`` and ``rlu envs best-behaviour``: the two references of the Atari
normalisation, measured or recomputed and stored with provenance."""

from __future__ import annotations

import argparse
import os
from typing import Any

from rlu.commands._options import checked
from rlu.domains import DOMAINS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("envs", help="environment tools")
    envs = p.add_subparsers(dest="envs_command", required=True, metavar="ENVS_COMMAND")
    r = envs.add_parser(
        "random-scores",
        help="measure uniform-random returns per task (Atari normalisation needs them)",
    )
    r.add_argument("--domain", action="append", help="a domain to measure (repeatable)")
    r.add_argument("--task", action="append", help="a task id to measure (repeatable)")
    r.add_argument(
        "--episodes",
        type=checked(int, {"min": 1}, "--episodes"),
        default=100,
        help="episodes per task (default 100, what the shipped Atari scores hold)",
    )
    r.add_argument("--seed", type=checked(int, {"min": 0}, "--seed"), default=0)
    r.add_argument(
        "--atari-max-steps",
        type=int,
        default=None,
        help="Atari episode cap in agent steps (default: the env's 27,000); recorded per task",
    )
    r.add_argument(
        "--camera",
        action="store_true",
        help="render the locomotion camera (off by default: returns do not depend on it)",
    )
    r.add_argument("--out", default="random_scores.json", help="JSON file to write")
    r.add_argument(
        "--resume",
        action="store_true",
        help="keep the tasks of --out that already hold --episodes episodes of this --seed and "
        "settings, measure the rest (an interrupted run loses one task per worker at most)",
    )
    r.add_argument(
        "--workers",
        type=checked(int, {"min": 1}, "--workers"),
        default=1,
        help="processes measuring tasks in parallel (default 1); the numbers do not depend on it",
    )
    r.set_defaults(func=_random_scores)

    b = envs.add_parser(
        "best-behaviour",
        help="recompute the Atari best-behaviour scores from downloaded release files",
        description="Best snapshot of the data-generating DQN per game: from each run's "
        "atari_episodes_ordered shards (one per checkpoint), the checkpoint with the highest "
        "mean raw episode return, averaged over the runs found. Reads FILE... or every "
        "downloaded shard under a bucket-shaped --src ROOT; writes an "
        "rlu.atari_best_behaviour/1 file (the format of rlu/resources/atari_best_behaviour.json).",
    )
    b.add_argument("files", nargs="*", metavar="FILE", help="atari_episodes_ordered shards")
    b.add_argument("--task", action="append", help="an Atari task id (repeatable; with --src)")
    b.add_argument("--src", help="bucket-shaped root holding downloaded shards")
    b.add_argument("--run", action="append", help="with --src: run 1..5 (repeatable; default all)")
    b.add_argument("--no-verify", action="store_true", help="skip the record CRC checks")
    b.add_argument("--out", default="atari_best_behaviour.json", help="JSON file to write")
    b.set_defaults(func=_best_behaviour)


def _random_scores(args: argparse.Namespace) -> int:
    from rlu.envs import scores
    from rlu.tasks import list_tasks
    from rlu.types import RluError

    if args.episodes < 1:
        raise RluError("--episodes must be >= 1")
    chosen = []
    for t in list_tasks():
        if args.task and t.id not in args.task:
            continue
        if args.domain and t.domain not in args.domain:
            continue
        if DOMAINS[t.domain].data_only and not args.task:
            continue  # no env to play (a task named with --task gets the domain's refusal)
        chosen.append(t)
    if args.task:
        known = {t.id for t in chosen}
        missing = [x for x in args.task if x not in known]
        if missing:
            raise RluError(f"unknown task id(s) {missing}; `rlu list` prints every id")
    jobs = []
    for t in chosen:
        settings: dict = {}
        dom = DOMAINS[t.domain]
        if dom.step_limit_setting and args.atari_max_steps:
            settings[dom.step_limit_setting] = args.atari_max_steps
        if dom.camera_setting:
            settings[dom.camera_setting] = bool(args.camera)
        for challenge in dom.challenges or ("none",):
            jobs.append((t.id, challenge, settings))
    existing = scores.load(args.out) if args.resume and os.path.exists(args.out) else None
    kept = []
    if existing is not None:
        file_seed, have = existing["provenance"].get("seed"), existing["scores"]
        kept = [
            k
            for t, c, s in jobs
            if (k := scores.score_key(t, c)) in have
            and scores.is_complete(have[k], args.episodes, args.seed, s, file_seed)
        ]
        print(f"{args.out}: keeping {len(kept)} of {len(jobs)} tasks, measuring the rest")
    total = len(jobs) - len(kept)
    count = 0

    def progress(key: str, entry: dict) -> None:
        nonlocal count
        count += 1
        print(
            f"[{count}/{total}] {key}: mean {entry['mean']:.2f} ± {entry['std']:.2f} over "
            f"{entry['episodes']} episodes (lengths {min(entry['lengths'])}-"
            f"{max(entry['lengths'])}; {entry['cpu_seconds']:.0f} CPU s)",
            flush=True,
        )
        scores.write(doc, args.out)  # after every task, so a crash loses one task per worker

    doc = existing or scores.measure([], args.episodes, args.seed)
    scores.measure(
        jobs, args.episodes, args.seed, progress=progress, existing=doc, workers=args.workers
    )
    scores.write(doc, args.out)
    print(f"wrote {len(doc['scores'])} tasks to {args.out}")
    return 0


def _release_files(src: str, task_id: str, runs: list[str] | None) -> list[str]:
    """Every downloaded ``atari_episodes_ordered`` shard of ``task_id`` under ``src``."""
    from rlu.data.release import catalog
    from rlu.tasks import get_task
    from rlu.types import RluError

    task = get_task(task_id)
    if not DOMAINS[task.domain].normalised:  # only a normalised domain has best-behaviour scores
        raise RluError(f"{task_id} is not an Atari task; best-behaviour scores are Atari's")
    files: list[str] = []
    for run in runs or list(task.datasets):
        sel = catalog.select(task_id, "atari_episodes_ordered", run)
        try:
            found = catalog.find_shards(src, sel)
        except RluError:
            if runs:  # a run asked for by name must be there
                raise
            continue
        files.extend(found)
    if not files:
        raise RluError(
            f"no atari_episodes_ordered shards of {task_id} under {src}; fetch them with "
            f"`rlu download {task_id} --family atari_episodes_ordered --run N`"
        )
    return files


def _best_behaviour(args: argparse.Namespace) -> int:
    import datetime as dt

    from rlu.evaluation import reference
    from rlu.types import RluError

    jobs: list[tuple[str, list[str]]] = []
    if args.src:
        if args.files:
            raise RluError("give either FILE... or --src ROOT with --task, not both")
        if not args.task:
            raise RluError("--src needs --task atari/GAME (repeatable)")
        jobs = [(t, _release_files(args.src, t, args.run)) for t in args.task]
    else:
        if not args.files:
            raise RluError("no release files; give FILE... (with one --task) or --src ROOT")
        if args.run:
            raise RluError("--run picks runs under --src; with FILE... list the files instead")
        if not args.task or len(args.task) != 1:
            raise RluError("with FILE... say which game they are: one --task atari/GAME")
        jobs = [(args.task[0], list(args.files))]
    scores: dict[str, Any] = {}
    doc = {
        "format": reference.FORMAT,
        "provenance": {
            "source": "recomputed from rl_unplugged atari_episodes_ordered release files",
            "statistic": "per run, the checkpoint with the highest mean raw episode_return; "
            "averaged over the runs found",
            "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        },
        "scores": scores,
    }
    for task_id, files in jobs:
        entry = reference.best_behaviour_from_release(files, verify=not args.no_verify)
        entry["files"] = len(files)
        scores[task_id] = entry
        runs = ", ".join(f"run {r}: ckpt {v['checkpoint']} {v['mean']:.2f}"
                         for r, v in entry["runs"].items())  # fmt: skip
        print(f"{task_id}: {entry['mean']:.2f} ({runs})", flush=True)
    reference.write(args.out, doc)
    print(f"wrote {len(doc['scores'])} games to {args.out}")
    return 0
