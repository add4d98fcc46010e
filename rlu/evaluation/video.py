"""Videos of evaluation episodes: a policy's rollouts written as MP4 (or GIF), with their returns.

    from rlu.evaluation.rollout import task_env_factory
    from rlu.evaluation.video import record_video

    env_fn = task_env_factory("control_suite/cartpole_swingup", render_mode="rgb_array")
    videos = record_video(policy, env_fn, "videos", num_episodes=2, seed=0)
    videos[0].path, videos[0].episode_return      # videos/episode_000.mp4, its return

``rlu evaluate RUN --video DIR`` does this for a trained run. The policy is a
``rlu.types.Policy`` (batched observations, episode starts and previous rewards -> batched
actions), called with a batch of one.

- Episode ``i`` is reset with the seed that episode ``i`` of
  ``rlu.evaluation.rollout.evaluate(..., seed=seed)`` gets, so a deterministic policy's video
  shows the very episode whose return the evaluation lists. A network acting on a batch of one
  here and on the evaluation's batch of ``num_envs`` may round its actions' last bits
  differently, and a long episode can drift from that: a trained IQL's filmed cartpole episode
  returned 336.3 where ``rlu evaluate`` (4 envs) listed 336.8 for it.
- Frames: one at the reset and one after every step, from ``env.render()`` (the env must be made
  with ``render_mode="rgb_array"``), played at the env's ``metadata["render_fps"]``, i.e. in real
  time. Frames under 240 pixels high (Atari's 210x160 screen) are enlarged by an integer factor,
  pixels kept square and sharp. A strip under each frame says the episode, step and return so far
  (``caption=False`` leaves it out).
- MP4: H.264 (yuv420p, what browsers and players read) encoded by the ffmpeg binary that the
  imageio-ffmpeg wheel ships, so nothing outside pip is needed (the ``video`` extra). Frames
  stream to ffmpeg as they come: any episode length fits in memory. GIF (``fmt="gif"``) needs
  only Pillow but holds every frame (one byte a pixel) until the episode ends: for short
  episodes; it plays at most 50 frames a second, so a faster env keeps every k-th frame.
- Each video is written under a temporary name and renamed when its episode is over, and
  ``DIR/videos.json`` lists every video with its seed, return and length, so an interrupted
  recording leaves no half-written file.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rlu.evaluation.rollout import EnvFactory, _inference_mode, _stack, episode_seed
from rlu.files import write_json
from rlu.system import install_hint
from rlu.types import Policy, RluError

FORMATS = ("mp4", "gif")
INDEX = "videos.json"
MIN_HEIGHT = 240
"""Frames lower than this are enlarged by the smallest integer factor that reaches it."""
CAPTION_HEIGHT = 24


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
        return asdict(self)


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
    ``rgb_array``) into ``out_dir/<name>_<i>.<fmt>``; see the module docstring."""
    if num_episodes < 1:
        raise RluError(f"num_episodes={num_episodes}; film at least one episode")
    open_writer = check_format(fmt)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    env = env_fn()
    videos = []
    try:
        if env.render_mode != "rgb_array":
            raise RluError(
                f"the env renders {env.render_mode!r}; a video needs one made with "
                "render_mode='rgb_array' (task_env_factory(task, render_mode='rgb_array'))"
            )
        fps = float(env.metadata["render_fps"])
        with _inference_mode():
            for i in range(num_episodes):
                path = out / f"{name}_{i:03d}.{fmt}"
                s = episode_seed(seed, i)
                ret, length = _film(policy, env, i, s, max_steps, path, open_writer, fps, caption)
                videos.append(Video(str(path), i, s, ret, length, fps))
    finally:
        env.close()
    index = {"seed": seed, "videos": [v.to_json() for v in videos]}
    write_json(out / INDEX, index, indent=1)
    return videos


def _film(policy, env, episode, seed, max_steps, path, open_writer, fps, caption) -> tuple:
    obs, _ = env.reset(seed=seed)
    total, t = 0.0, 0
    frames = _Frames(caption, f"episode {episode}")
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    first = frames(env.render(), t, total)
    writer = open_writer(tmp, first.shape, fps)
    try:
        writer(first)
        is_first = np.ones(1, bool)
        reward = np.zeros(1, np.float64)
        done = False
        while not done:
            action = np.asarray(policy(_stack([obs]), is_first.copy(), reward.copy()))[0]
            is_first[:] = False
            obs, r, terminated, truncated, _ = env.step(action)
            reward[0] = float(r)
            total += float(r)
            t += 1
            done = terminated or truncated or (max_steps is not None and t >= max_steps)
            writer(frames(env.render(), t, total))
        writer(None)  # finish the file
    except BaseException:
        writer.abort()
        if tmp.exists():
            tmp.unlink()
        raise
    os.replace(tmp, path)
    return total, t


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

    def open_writer(path: Path, shape: tuple, fps: float) -> _Writer:
        h, w = shape[:2]
        gen = imageio_ffmpeg.write_frames(
            str(path),
            (w, h),
            fps=fps,
            codec="libx264",
            pix_fmt_out="yuv420p",
            macro_block_size=1,  # sides are made even here; no rescaling by imageio-ffmpeg
            quality=7,  # crf 15: sharp edges on the flat colours of these scenes
            ffmpeg_log_level="error",
        )
        gen.send(None)

        def add(frame: np.ndarray | None) -> None:
            if frame is None:
                gen.close()
                return
            if frame.shape != shape:
                raise RluError(f"env.render() changed frame size mid-episode: {frame.shape}")
            gen.send(frame)

        return _Writer(add, gen.close)

    return open_writer


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
