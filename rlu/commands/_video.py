"""``rlu evaluate RUN --video DIR``: videos of the episodes the evaluation scores.

The flags are added to the ``evaluate`` parser by ``add_video_options``; ``check_video_options``
runs before anything else (the folder, the counts, the size and the extra are checked before a
policy is loaded); ``evaluation_watch`` is what watches the evaluation: its progress (episodes
done, steps so far) and, with ``--video``, a ``rlu.evaluation.video.Recorder`` that films the
first ``--video-episodes`` of the episodes it scores, as they are played; ``report_videos``
prints one line a video after the returns.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterator
from typing import Any


def add_video_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--video",
        metavar="DIR",
        default=None,
        help="also film the first --video-episodes of the episodes the evaluation scores, as "
        "they are played, into DIR/episode_NNN.mp4, with DIR/videos.json listing their returns "
        "(the 'video' extra); DIR is made, or must be a video folder or empty",
    )
    p.add_argument(
        "--video-episodes",
        type=int,
        default=1,
        metavar="N",
        help="episodes to film with --video: the first N scored (default 1)",
    )
    p.add_argument(
        "--video-format",
        choices=["mp4", "gif"],
        default="mp4",
        help="mp4 (H.264, default) or gif (Pillow only; short episodes)",
    )
    p.add_argument(
        "--video-size",
        default=None,
        metavar="WIDTHxHEIGHT",
        type=_size,
        help="frame size of MuJoCo envs, e.g. 320x240 (default: 640x480; Atari films the ALE's "
        "screen, enlarged to at least 240 pixels high)",
    )


def _size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` -> (height, width), each side 16 to 4096 pixels."""
    w, sep, h = text.lower().partition("x")
    try:
        width, height = int(w), int(h)
    except ValueError:
        width = height = 0
    if not sep or not (16 <= width <= 4096 and 16 <= height <= 4096):
        raise argparse.ArgumentTypeError(
            f"{text!r}; write it as WIDTHxHEIGHT, each 16 to 4096 pixels, e.g. 320x240"
        )
    return height, width


def check_video_options(args: argparse.Namespace) -> None:
    """Fail now on what would fail later: a bad count, a missing extra, a video folder that is
    empty-named, a symbolic link, an input (the run, its dataset) or something rlu did not make
    (a dataset, a run, a sweep: any non-empty folder without videos.json)."""
    from pathlib import Path

    from rlu.evaluation.video import INDEX, check_format
    from rlu.files import check_output
    from rlu.training import runs
    from rlu.types import RluError

    if args.video_episodes < 1:
        raise RluError(f"--video-episodes {args.video_episodes}; film at least one")
    if args.video_episodes > args.eval_episodes:
        raise RluError(
            f"--video-episodes {args.video_episodes} is more than the {args.eval_episodes} "
            "episodes the evaluation scores (--eval-episodes); the videos are of scored episodes"
        )
    check_format(args.video_format)
    if str(args.video).strip() and Path(args.video).is_symlink():
        raise RluError(
            f"--video {args.video} is a symbolic link; rlu writes videos only into a real "
            "folder: give the folder itself, or a new one"
        )
    run, _ = runs.find_run(args.run)
    inputs: list[str | Path] = [run]
    dataset = _recorded_dataset(run)
    if dataset is not None:
        inputs.append(dataset)
    check_output(args.video, inputs, INDEX, "video folder", "--video")


def _recorded_dataset(run: Any) -> str | None:
    """The dataset folder a run's config.json names, if it reads as one."""
    from rlu.training.restore import read_run
    from rlu.types import RluError

    try:
        resolved, _, _ = read_run(run)
    except RluError:
        return None  # the evaluation says what is wrong with the run
    return str(resolved["dataset"]["path"])


class _Watch:
    """The evaluation's observer: progress (episodes done, steps so far) and the recorder."""

    def __init__(self, bar: Any, recorder: Any, render: dict[str, Any] | None):
        self.bar, self.recorder, self.render = bar, recorder, render
        self.steps = 0

    def reset(self, episode: int, env: Any) -> None:
        if self.recorder is not None:
            self.recorder.reset(episode, env)

    def step(self, episode: int, env: Any, reward: float, done: bool) -> None:
        if self.recorder is not None:
            self.recorder.step(episode, env, reward, done)
        self.steps += 1
        if done:
            self.bar.update(1)
        self.bar.set_postfix(steps=self.steps)


@contextlib.contextmanager
def evaluation_watch(args: argparse.Namespace, bar: Any) -> Iterator[_Watch]:
    """The observer of ``rlu evaluate``'s episodes: ``bar`` (a ``rlu.progress.Progress`` over
    the episodes) and, with ``--video``, the recorder, which says first which episodes it
    films; its ``render`` are the env settings filming needs (None without ``--video``)."""
    if args.video is None:
        yield _Watch(bar, None, None)
        return
    from rlu.evaluation.video import Recorder

    n = args.video_episodes
    which = "episode 0" if n == 1 else f"episodes 0-{n - 1}"
    print(
        f"rlu evaluate: filming {which} of the {args.eval_episodes} it scores, as they are "
        f"played, into {args.video}",
        file=sys.stderr,
    )
    render: dict[str, Any] = {"render_mode": "rgb_array"}
    if args.video_size is not None:
        render["render_size"] = args.video_size
    with Recorder(args.video, n, args.seed, fmt=args.video_format) as recorder:
        yield _Watch(bar, recorder, render)


def report_videos(args: argparse.Namespace, recorder: Any) -> None:
    """One line a video on stdout (none with ``--json``: DIR/videos.json holds them)."""
    if args.json:
        return
    for v in recorder.videos:
        print(f"{v.path}: episode {v.episode}, return {v.episode_return:.1f}, {v.length} steps")
