"""Videos of evaluation episodes on the real envs, read back with ffmpeg and Pillow."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("gymnasium")
imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
pytest.importorskip("PIL")

from rlu.evaluation.rollout import episode_seed, evaluate, task_env_factory  # noqa: E402
from rlu.evaluation.video import INDEX, record_video  # noqa: E402
from rlu.types import RluError  # noqa: E402

CARTPOLE = "control_suite/cartpole_swingup"


def _swing(obs, is_first, reward):
    """A deterministic policy that pushes the cart along its velocity (it swings the pole)."""
    v = np.asarray(obs["velocity"])[:, :1]
    return np.where(v >= 0, 1.0, -1.0).astype(np.float32)


def _frames(path):
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    return meta, [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in gen]


def test_an_mp4_per_episode_with_the_evaluation_s_returns(tmp_path):
    pytest.importorskip("dm_control")
    env_fn = task_env_factory(CARTPOLE, render_mode="rgb_array")
    videos = record_video(_swing, env_fn, tmp_path / "v", num_episodes=2, seed=7, max_steps=25)
    ev = evaluate(_swing, env_fn, num_episodes=2, seed=7, num_envs=1, max_steps=25)
    assert [v.episode_return for v in videos] == list(ev.returns)  # the same two episodes
    assert [v.length for v in videos] == [25, 25]
    assert [v.seed for v in videos] == [episode_seed(7, 0), episode_seed(7, 1)]
    meta, frames = _frames(videos[0].path)
    assert meta["codec"] == "h264" and meta["fps"] == 100.0  # cartpole steps 0.01 s: real time
    assert len(frames) == 26 and frames[0].shape == (480 + 24, 640, 3)  # frame + caption strip
    # the first frame is the env's own frame after the seeded reset (up to H.264's loss)
    env = env_fn()
    env.reset(seed=videos[0].seed)
    drawn = env.render().astype(int)
    env.close()
    assert np.abs(frames[0][:480].astype(int) - drawn).mean() < 3
    assert np.abs(frames[-1][:480].astype(int) - drawn).mean() > 0.5  # the cart moved
    index = json.loads((tmp_path / "v" / INDEX).read_text())
    assert [v["episode_return"] for v in index["videos"]] == list(ev.returns)
    assert sorted(p.name for p in (tmp_path / "v").iterdir()) == [
        "episode_000.mp4",
        "episode_001.mp4",
        INDEX,
    ]


def test_gif_keeps_real_time_at_50_frames_a_second(tmp_path):
    pytest.importorskip("dm_control")
    from PIL import Image

    env_fn = task_env_factory(CARTPOLE, render_mode="rgb_array")
    (v,) = record_video(_swing, env_fn, tmp_path, max_steps=20, fmt="gif", caption=False)
    with Image.open(v.path) as gif:
        assert (gif.n_frames, gif.size, gif.info["duration"]) == (11, (640, 480), 20)


def test_atari_frames_are_enlarged_with_square_pixels(tmp_path):
    pytest.importorskip("ale_py")
    env_fn = task_env_factory("atari/Pong", render_mode="rgb_array")
    (v,) = record_video(lambda o, f, r: np.zeros(len(f), np.int64), env_fn, tmp_path, max_steps=6)
    meta, frames = _frames(v.path)
    assert meta["fps"] == 15.0 and len(frames) == 7
    assert frames[0].shape == (2 * 210 + 24, 2 * 160, 3)
    env = env_fn()
    env.reset(seed=v.seed)
    screen = env.render().repeat(2, axis=0).repeat(2, axis=1).astype(int)
    env.close()
    assert np.abs(frames[0][:420].astype(int) - screen).mean() < 4


def test_an_env_without_frames_or_a_bad_format_is_refused_and_nothing_written(tmp_path):
    pytest.importorskip("dm_control")
    with pytest.raises(RluError, match="needs one made with render_mode='rgb_array'"):
        record_video(_swing, task_env_factory(CARTPOLE), tmp_path / "a")
    assert list((tmp_path / "a").iterdir()) == []
    with pytest.raises(RluError, match="use one of mp4, gif"):
        record_video(_swing, task_env_factory(CARTPOLE), tmp_path / "b", fmt="avi")


def test_a_failing_policy_leaves_no_half_written_video(tmp_path):
    pytest.importorskip("dm_control")
    calls = []

    def breaks(obs, is_first, reward):
        calls.append(1)
        if len(calls) > 5:
            raise RuntimeError("policy died")
        return _swing(obs, is_first, reward)

    env_fn = task_env_factory(CARTPOLE, render_mode="rgb_array")
    with pytest.raises(RuntimeError, match="policy died"):
        record_video(breaks, env_fn, tmp_path, max_steps=50)
    assert list(tmp_path.iterdir()) == []


def test_rlu_evaluate_video_films_a_trained_run(tmp_path, capsys):
    """A (very) short BC run on the shipped cartpole data, evaluated with --video."""
    pytest.importorskip("torch")
    pytest.importorskip("dm_control")
    import rlu
    from rlu.cli import main
    from rlu.settings import RunSettings
    from rlu.train import TrainConfig, train

    data = str(rlu.load_dataset(CARTPOLE).path)
    run = RunSettings(steps=20, eval_every=-1, checkpoint_every=20)
    cfg = TrainConfig(task=CARTPOLE, agent="bc", dataset=data, run=run)
    train(cfg, tmp_path / "run", progress=False)
    argv = ["evaluate", str(tmp_path / "run"), "--episodes", "2", "--envs", "1", "--max-steps",
            "30", "--video", str(tmp_path / "v"), "--video-episodes", "2"]  # fmt: skip
    assert main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    returns = [float(r) for r in lines[0].split("returns ")[1].split(", ")]
    filmed = [float(line.split("return ")[1].split(",")[0]) for line in lines[1:]]
    assert len(filmed) == 2 and filmed == returns  # both printed with one decimal
    assert lines[1].startswith(str(tmp_path / "v" / "episode_000.mp4"))
    assert len(_frames(tmp_path / "v" / "episode_001.mp4")[1]) == 31
    assert main([*argv[:-2], "--video-episodes", "0"]) == 2
    assert "--video-episodes 0; film at least one" in capsys.readouterr().err
