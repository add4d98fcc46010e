"""Videos of evaluation episodes: a policy's rollouts written as MP4 (or GIF), with their returns.

    from rlu.evaluation.rollout import task_env_factory
    from rlu.evaluation.video import record_video

    env_fn = task_env_factory("control_suite/cartpole_swingup", render_mode="rgb_array")
    videos = record_video(policy, env_fn, "videos", num_episodes=2, seed=0)
    videos[0].path, videos[0].episode_return      # videos/episode_000.mp4, its return

``rlu evaluate RUN --video DIR`` films the episodes it scores: a :class:`Recorder` watches the
evaluation (``rlu.evaluation.rollout.evaluate(..., observer=recorder)``) and films the episodes
it is given as they are played and scored, so each video's return is the one the evaluation
lists for that episode, whatever the number of envs stepped in lockstep. ``record_video`` is the
same with one env. The policy is a ``rlu.types.Policy`` (batched observations, episode starts
and previous rewards -> batched actions).

- Episode ``i`` is episode ``i`` of the evaluation: reset with ``episode_seed(seed, i)``.
- Frames: one at the reset and one after every step, from ``env.render()`` (the env must be made
  with ``render_mode="rgb_array"``; MuJoCo envs take ``render_size=(height, width)``), played at
  the env's ``metadata["render_fps"]``, i.e. in real time. Frames under 240 pixels high (Atari's
  210x160 screen) are enlarged by an integer factor, pixels kept square and sharp. A strip under
  each frame says the episode, step and return so far (``caption=False`` leaves it out).
- MP4: H.264 (yuv420p, what browsers and players read) encoded by the ffmpeg binary that the
  imageio-ffmpeg wheel ships (or ``$IMAGEIO_FFMPEG_EXE``), so nothing outside pip is needed (the
  ``video`` extra). Frames stream to ffmpeg as they come: any episode length fits in memory. An
  ffmpeg that takes no frame for ``ENCODER_TIMEOUT`` seconds, or does not finish the file that
  long after its last frame, is stopped and the recording fails with an error saying so. GIF
  (``fmt="gif"``) needs only Pillow but holds every frame (one byte a pixel) until the episode
  ends: for short episodes; it plays at most 50 frames a second, so a faster env keeps every
  k-th frame.
- Each video is written to a temporary with an unpredictable name beside it
  (``rlu.files.atomic_path``) and renamed when its episode is over; a link planted at a video's
  name is refused, and ``DIR/videos.json`` lists every video with its seed, return and length,
  so an interrupted recording leaves no half-written file.
"""

from __future__ import annotations

import contextlib
import math
import os
import select
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from rlu.evaluation.rollout import EnvFactory, episode_seed, evaluate
from rlu.files import atomic_path, check_targets, make_folder, write_json
from rlu.system import install_hint
from rlu.types import Policy, RluError

__all__ = [
    "CAPTION_HEIGHT",
    "ENCODER_TIMEOUT",
    "FORMATS",
    "INDEX",
    "MIN_HEIGHT",
    "Recorder",
    "Video",
    "check_format",
    "record_video",
]

FORMATS = ("mp4", "gif")
"""The video formats: H.264 MP4 (the ``video`` extra) or GIF (Pillow only)."""
INDEX = "videos.json"
"""The file in a video folder that lists its videos (seed, return, length of each)."""
MIN_HEIGHT = 240
"""Frames lower than this are enlarged by the smallest integer factor that reaches it."""
CAPTION_HEIGHT = 24
"""Pixels of the caption strip under each frame."""
ENCODER_TIMEOUT = 60.0
"""Seconds ffmpeg may take to accept one frame, or to finish a file after its last frame,
before it is stopped and the recording fails."""


@dataclass(frozen=True)
class Video:
    """One recorded episode."""

    path: str
    episode: int
    """Episode index; its reset seed is ``episode_seed(seed, episode)``."""
    seed: int
    """The reset seed of the episode."""
    episode_return: float
    """Undiscounted return (for Atari the raw game score, as evaluation sums it)."""
    length: int
    """Agent steps; the video has ``length + 1`` frames."""
    fps: float

    def to_json(self) -> dict[str, Any]:
        """The video's entry in ``videos.json``."""
        return asdict(self)


class Recorder:
    """Films episodes of an evaluation while it scores them: pass it as
    ``evaluate(..., observer=recorder)`` on envs made with ``render_mode="rgb_array"``.

    Args:
        out_dir: the video folder (made if missing; a symbolic link there is refused).
        episodes: the episode indices to film (``3``: the first three).
        seed: the evaluation's seed (recorded with each video).
        fmt: ``"mp4"`` or ``"gif"``.
        caption: draw the strip with the episode, step and return under each frame.
        name: videos are ``out_dir/<name>_<i>.<fmt>``.

    Use it as a context manager (or call :meth:`close`): on success it writes ``videos.json``;
    after an error it removes every video still being written. ``videos`` holds the finished
    ones, in episode order.
    """

    def __init__(
        self,
        out_dir: str | os.PathLike,
        episodes: int | Iterable[int],
        seed: int = 0,
        fmt: str = "mp4",
        caption: bool = True,
        name: str = "episode",
    ) -> None:
        self.out = Path(out_dir)
        self.episodes = frozenset(range(episodes) if isinstance(episodes, int) else episodes)
        if not self.episodes or min(self.episodes) < 0:
            raise RluError(f"episodes {sorted(self.episodes)}; film at least one episode (>= 0)")
        self.seed = seed
        self.fmt = fmt
        self.caption = caption
        self.name = name
        self.open_writer = check_format(fmt)
        # every file to be replaced, before the first is: a link planted at a later episode's
        # video must not leave the earlier ones replaced
        names = [f"{name}_{e:03d}.{fmt}" for e in sorted(self.episodes)]
        check_targets(self.out, [*names, INDEX])
        self.videos: list[Video] = []
        self._open: dict[int, _Filming] = {}
        self._closed = False

    # --- the observer (rlu.evaluation.rollout.EpisodeObserver) ------------------------------
    def reset(self, episode: int, env: Any) -> None:
        """Episode ``episode`` starts on ``env``: its first frame, if it is filmed."""
        if episode not in self.episodes:
            return
        if env.render_mode != "rgb_array":
            raise RluError(
                f"the env renders {env.render_mode!r}; a video needs one made with "
                "render_mode='rgb_array' (task_env_factory(task, render_mode='rgb_array'))"
            )
        make_folder(self.out)
        path = self.out / f"{self.name}_{episode:03d}.{self.fmt}"
        fps = float(env.metadata["render_fps"])
        frames = _Frames(self.caption, f"episode {episode}")
        film = _Filming(path, episode, episode_seed(self.seed, episode), fps, frames)
        self._open[episode] = film
        film.start(env.render(), self.open_writer)

    def step(self, episode: int, env: Any, reward: float, done: bool) -> None:
        """Episode ``episode`` took a step on ``env``: its frame; its file when ``done``."""
        film = self._open.get(episode)
        if film is None:
            return
        film.add(env.render(), reward)
        if done:
            del self._open[episode]
            self.videos.append(film.finish())
            self.videos.sort(key=lambda v: v.episode)

    # --- the end ------------------------------------------------------------------------------
    def close(self, failed: bool = False) -> None:
        """Write ``videos.json`` (unless ``failed``); drop every video not finished."""
        if self._closed:
            return
        self._closed = True
        for film in self._open.values():
            film.abort()
        unfinished = sorted(self._open)
        self._open.clear()
        if failed:
            return
        if unfinished:
            raise RluError(
                f"episodes {unfinished} were being filmed when the evaluation ended; their "
                "videos were dropped"
            )
        if self.videos:
            index = {"seed": self.seed, "videos": [v.to_json() for v in self.videos]}
            write_json(self.out / INDEX, index, indent=1)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close(failed=exc_type is not None)


def record_video(
    policy: Policy,
    env_fn: EnvFactory,
    out_dir: str | os.PathLike,
    num_episodes: int = 1,
    seed: int = 0,
    max_steps: int | None = None,
    fmt: str = "mp4",
    caption: bool = True,
    name: str = "episode",
) -> list[Video]:
    """Film ``num_episodes`` episodes of ``policy`` in envs from ``env_fn`` (which must render
    ``rgb_array``) into ``out_dir/<name>_<i>.<fmt>``: an evaluation of those episodes on one env
    (the same seeds, the same returns) with a :class:`Recorder`; see the module docstring."""
    if num_episodes < 1:
        raise RluError(f"num_episodes={num_episodes}; film at least one episode")
    recorder = Recorder(out_dir, num_episodes, seed, fmt, caption, name)
    make_folder(out_dir)
    with recorder:
        evaluate(policy, env_fn, num_episodes, seed, 1, max_steps, observer=recorder)
    return recorder.videos


class _Filming:
    """One episode being filmed: its frames into a temporary, renamed when it ends."""

    def __init__(self, path: Path, episode: int, seed: int, fps: float, frames: _Frames):
        self.path, self.episode, self.seed, self.fps, self.frames = path, episode, seed, fps, frames
        self.total, self.t = 0.0, 0
        self._stack = contextlib.ExitStack()
        self._writer: _Writer | None = None

    def start(self, frame: Any, open_writer: Callable[[Path, tuple, float], _Writer]) -> None:
        try:
            tmp = self._stack.enter_context(atomic_path(self.path, suffix=True))
            first = self.frames(frame, 0, 0.0)
            self._writer = open_writer(tmp, first.shape, self.fps)
            self._writer(first)
        except BaseException:
            self.abort()
            raise

    def add(self, frame: Any, reward: float) -> None:
        self.total += float(reward)
        self.t += 1
        try:
            assert self._writer is not None
            self._writer(self.frames(frame, self.t, self.total))
        except BaseException:
            self.abort()
            raise

    def finish(self) -> Video:
        try:
            assert self._writer is not None
            self._writer(None)  # finish the file
            self._writer = None
        except BaseException:
            self.abort()
            raise
        self._stack.close()  # the temporary renamed over the video's name
        return Video(str(self.path), self.episode, self.seed, self.total, self.t, self.fps)

    def abort(self) -> None:
        """Stop the encoder and remove the temporary."""
        if self._writer is not None:
            self._writer.abort()
            self._writer = None
        self._stack.__exit__(RluError, RluError("dropped"), None)  # the temporary removed


def check_format(fmt: str) -> Callable[[Path, tuple, float], _Writer]:
    """The writer of ``fmt``; an unknown format or a missing package is an RluError now."""
    if fmt not in FORMATS:
        raise RluError(f"video format {fmt!r}; use one of {', '.join(FORMATS)}")
    try:
        import PIL  # noqa: F401  (the caption strip, and GIFs)
    except ImportError:
        raise RluError(f"videos need Pillow: {install_hint('video')}") from None
    return _mp4_writer() if fmt == "mp4" else _gif_writer()


class _Frames:
    """Frames as written: enlarged if small, a caption strip below, sides padded to even
    numbers (H.264's 4:2:0 chroma needs them)."""

    def __init__(self, caption: bool, label: str) -> None:
        self.caption = caption
        self.label = label
        self._font: Any = None

    def __call__(self, frame: Any, step: int, ret: float) -> np.ndarray:
        frame = np.asarray(frame)
        if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
            raise RluError(
                f"env.render() gave {frame.dtype} {frame.shape}; a video frame is (H, W, 3) uint8"
            )
        k = max(1, math.ceil(MIN_HEIGHT / frame.shape[0]))
        if k > 1:
            frame = frame.repeat(k, axis=0).repeat(k, axis=1)
        if self.caption:
            frame = np.concatenate([frame, self._strip(frame.shape[1], step, ret)], axis=0)
        h, w = frame.shape[:2]
        if h % 2 or w % 2:
            frame = np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)))
        return np.ascontiguousarray(frame)

    def _strip(self, width: int, step: int, ret: float) -> np.ndarray:
        from PIL import Image, ImageDraw, ImageFont

        if self._font is None:
            self._font = ImageFont.load_default(size=15)
        img = Image.new("RGB", (width, CAPTION_HEIGHT))
        text = f"{self.label}   step {step}   return {ret:.1f}"
        ImageDraw.Draw(img).text((6, 3), text, fill=(255, 255, 255), font=self._font)
        return np.asarray(img)


class _Writer:
    """Takes frames; ``writer(None)`` finishes the file, ``abort()`` drops it."""

    def __init__(self, add: Callable[[np.ndarray | None], None], abort: Callable[[], None]):
        self._add, self.abort = add, abort

    def __call__(self, frame: np.ndarray | None) -> None:
        self._add(frame)


def _mp4_writer() -> Callable[[Path, tuple, float], _Writer]:
    try:
        import imageio_ffmpeg
    except ImportError:
        raise RluError(
            f"MP4 videos need the 'video' extra (imageio-ffmpeg, which ships ffmpeg): "
            f"{install_hint('video')}; or pass fmt='gif' (Pillow only)"
        ) from None
    try:
        exe = imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError as e:
        raise RluError(f"no ffmpeg for MP4 videos ({e}); {install_hint('video')}") from None

    def open_writer(path: Path, shape: tuple, fps: float) -> _Writer:
        return _ffmpeg(exe, path, shape, fps)

    return open_writer


def _ffmpeg(exe: str, path: Path, shape: tuple, fps: float) -> _Writer:
    """An ffmpeg process encoding raw RGB frames from a pipe into H.264 ``path``, every write
    and the final wait bounded by ``ENCODER_TIMEOUT``."""
    h, w = shape[:2]
    rate = str(Fraction(fps).limit_denominator())
    cmd = [exe, "-y", "-loglevel", "error", "-f", "rawvideo", "-vcodec", "rawvideo",
           "-s", f"{w}x{h}", "-pix_fmt", "rgb24", "-r", rate, "-i", "-", "-an",
           "-vcodec", "libx264", "-pix_fmt", "yuv420p",
           "-crf", "15",  # sharp edges on the flat colours of these scenes
           "-f", "mp4", str(path)]  # fmt: skip
    log = tempfile.TemporaryFile()  # noqa: SIM115 (closed with the writer; read on failure)
    try:
        proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=log, close_fds=True
        )
    except OSError as e:
        log.close()
        raise RluError(
            f"ffmpeg {exe} cannot be started ({e.strerror}); {install_hint('video')}"
        ) from None
    stdin = proc.stdin
    assert stdin is not None
    fd = stdin.fileno()
    os.set_blocking(fd, False)

    def said() -> str:
        log.seek(0)
        text = " ".join(log.read(2000).decode(errors="replace").split())
        return f": {text}" if text else ""

    def stop() -> None:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        with contextlib.suppress(OSError):
            stdin.close()
        log.close()

    def failed(why: str) -> RluError:
        stop_text = said() if not log.closed else ""
        stop()
        return RluError(f"ffmpeg ({exe}) {why} while writing {path}{stop_text}")

    def add(frame: np.ndarray | None) -> None:
        if frame is None:
            with contextlib.suppress(OSError):
                stdin.close()
            try:
                code = proc.wait(timeout=ENCODER_TIMEOUT)
            except subprocess.TimeoutExpired:
                why = f"did not finish the video {ENCODER_TIMEOUT:g} s after its last frame"
                raise failed(f"{why}; it may be hung (check `ffmpeg -version` runs)") from None
            if code != 0:
                raise failed(f"exited with code {code}")
            log.close()
            return
        if frame.shape != shape:
            why = f"got a frame of size {frame.shape} after {shape}"
            raise failed(f"{why} (the env's frames changed size mid-episode)")
        data = np.ascontiguousarray(frame).data.cast("B")
        deadline = time.monotonic() + ENCODER_TIMEOUT
        while len(data):
            left = deadline - time.monotonic()
            ready = select.select([], [fd], [], max(0.0, left))[1] if left > 0 else []
            if not ready:
                raise failed(
                    f"took no video frame for {ENCODER_TIMEOUT:g} s; it may be hung, or not "
                    "read its input (check `ffmpeg -version` runs; $IMAGEIO_FFMPEG_EXE picks "
                    "another ffmpeg)"
                )
            try:
                n = os.write(fd, data)
            except BlockingIOError:
                continue
            except (BrokenPipeError, OSError):
                proc.wait()
                raise failed(f"stopped reading frames (exit code {proc.returncode})") from None
            data = data[n:]

    return _Writer(add, stop)


def _gif_writer() -> Callable[[Path, tuple, float], _Writer]:
    try:
        from PIL import Image
    except ImportError:
        raise RluError(f"GIF videos need Pillow: {install_hint('video')}") from None

    def open_writer(path: Path, shape: tuple, fps: float) -> _Writer:
        frames: list[Any] = []
        # GIF delays are whole centiseconds and players slow delays under 2 to 10, so a GIF
        # plays at most 50 frames a second: faster envs keep every k-th frame (real time kept).
        stride = max(1, math.ceil(fps / 50))
        seen = [0]

        def add(frame: np.ndarray | None) -> None:
            if frame is not None:
                if seen[0] % stride == 0:
                    frames.append(Image.fromarray(frame).quantize(colors=256))
                seen[0] += 1
                return
            frames[0].save(
                path,
                format="GIF",
                save_all=True,
                append_images=frames[1:],
                duration=max(20, round(100 * stride / fps) * 10),
                loop=0,
            )

        return _Writer(add, frames.clear)

    return open_writer
