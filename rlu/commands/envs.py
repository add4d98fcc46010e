"""``rlu envs random-scores``: measure random-policy returns and store them with provenance."""

from __future__ import annotations

import argparse
import os


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("envs", help="environment tools")
    envs = p.add_subparsers(dest="envs_command", required=True, metavar="ENVS_COMMAND")
    r = envs.add_parser(
        "random-scores",
        help="measure uniform-random returns per task (Atari normalisation needs them)",
    )
    r.add_argument("--domain", action="append", help="a domain to measure (repeatable)")
    r.add_argument("--task", action="append", help="a task id to measure (repeatable)")
    r.add_argument("--episodes", type=int, default=5, help="episodes per task (default 5)")
    r.add_argument("--seed", type=int, default=0)
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
        "--resume", action="store_true", help="keep the tasks already in --out, measure the rest"
    )
    r.set_defaults(func=_random_scores)


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
        chosen.append(t)
    if args.task:
        known = {t.id for t in chosen}
        missing = [x for x in args.task if x not in known]
        if missing:
            raise RluError(f"unknown task id(s) {missing}; `rlu list` prints every id")
    jobs = []
    for t in chosen:
        settings: dict = {}
        if t.domain == "atari" and args.atari_max_steps:
            settings["max_episode_steps"] = args.atari_max_steps
        if t.domain == "locomotion":
            settings["camera"] = bool(args.camera)
        for challenge in ("none", "easy") if t.domain == "rwrl" else ("none",):
            jobs.append((t.id, challenge, settings))
    existing = scores.load(args.out) if args.resume and os.path.exists(args.out) else None

    def progress(key: str, entry: dict) -> None:
        print(
            f"{key}: mean {entry['mean']:.2f} ± {entry['std']:.2f} over {entry['episodes']} "
            f"episodes (lengths {min(entry['lengths'])}-{max(entry['lengths'])})",
            flush=True,
        )
        scores.write(doc, args.out)  # after every task, so a crash loses one task at most

    doc = existing or scores.measure([], args.episodes, args.seed)
    scores.measure(jobs, args.episodes, args.seed, progress=progress, existing=doc)
    scores.write(doc, args.out)
    print(f"wrote {len(doc['scores'])} tasks to {args.out}")
    return 0
