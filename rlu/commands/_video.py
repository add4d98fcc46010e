"""``rlu evaluate RUN --video DIR``: videos of a run's evaluation episodes.

The flags are added to the ``evaluate`` parser by ``add_video_options``; ``check_video_options``
runs before the evaluation (a missing extra fails at once, not after minutes of rollouts) and
``write_run_videos`` after it has printed its returns (and checked ``--challenge``). The
filming itself is ``rlu.evaluation.video.record_video``.
"""

from __future__ import annotations

import argparse
from typing import Any


def add_video_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--video",
        metavar="DIR",
        default=None,
        help="also film the first --video-episodes evaluation episodes (same seeds) into "
        "DIR/episode_NNN.mp4, with DIR/videos.json listing their returns (the 'video' extra)",
    )
    p.add_argument(
        "--video-episodes",
        type=int,
        default=1,
        metavar="N",
        help="episodes to film with --video (default 1)",
    )
    p.add_argument(
        "--video-format",
        choices=["mp4", "gif"],
        default="mp4",
        help="mp4 (H.264, default) or gif (Pillow only; short episodes)",
    )


def check_video_options(args: argparse.Namespace) -> None:
    """Fail now on what would fail after the evaluation: a bad count, a missing extra."""
    from rlu.evaluation.video import check_format
    from rlu.types import RluError

    if args.video_episodes < 1:
        raise RluError(f"--video-episodes {args.video_episodes}; film at least one")
    check_format(args.video_format)


def write_run_videos(args: argparse.Namespace) -> list[Any]:
    """Film the run's greedy policy in the env its evaluation used; print one line a video
    (none with ``--json``: DIR/videos.json holds them)."""
    from rlu.evaluation.rollout import task_env_factory
    from rlu.evaluation.video import record_video
    from rlu.restore import load_policy

    policy, resolved = load_policy(args.run, args.device)
    settings = dict(resolved["env_settings"])
    if args.challenge is not None:
        settings["challenge"] = args.challenge  # the evaluation before this checked it
    # --env as the evaluation took it: typed, so trusted (a run's recorded factory never is)
    task = resolved["train"]["task"]
    env_fn = task_env_factory(task, args.env, render_mode="rgb_array", **settings)
    videos = record_video(
        policy,
        env_fn,
        args.video,
        args.video_episodes,
        args.seed,
        args.max_steps,
        fmt=args.video_format,
    )
    if not args.json:
        for v in videos:
            print(f"{v.path}: episode {v.episode}, return {v.episode_return:.1f}, {v.length} steps")
    return videos
